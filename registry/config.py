"""A Distribution 2.8 registry's configuration pointed at this cloud as its token server: pure functions."""

from __future__ import annotations

import ipaddress
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

__all__ = [
    "ConfigProblem",
    "RegistrySetup",
    "check_realm",
    "is_loopback",
    "parse_listen",
    "render_config",
    "render_yaml",
]


class ConfigProblem(ValueError):
    """An argument of `registry_config` cannot make a working registry."""


@dataclass(frozen=True)
class RegistrySetup:
    """What a registry instance needs to know: where it listens and stores, and whom it trusts for tokens."""

    realm: str
    listen: str
    storage: Path
    rootcertbundle: Path
    service: str
    issuer: str
    http_secret: str
    tls_cert: Path | None = None
    tls_key: Path | None = None
    notify_url: str | None = None  # where pushes are told (the cloud's /api/registry/events)
    notify_token: str = ""  # what the registry presents there


def parse_listen(listen: str) -> tuple[str, int]:
    """Split HOST:PORT (an IPv6 host in brackets); raise ConfigProblem when either half is unusable."""
    host, sep, port_text = listen.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if not sep or not host or not port_text.isdigit() or not 0 < int(port_text) < 65536:
        raise ConfigProblem(f"--listen {listen!r} is not HOST:PORT (e.g. 127.0.0.1:5000)")
    return host, int(port_text)


def is_loopback(host: str) -> bool:
    """Tell whether a listen host is reachable from this machine only."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_realm(realm: str) -> None:
    """Refuse a realm that is not an absolute http(s) URL: the registry sends clients there."""
    parts = urlsplit(realm)
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise ConfigProblem(f"--realm {realm!r} is not an http(s) URL (e.g. http://127.0.0.1:8000/api/registry/token)")


def render_config(setup: RegistrySetup) -> dict[str, Any]:
    """Return the registry's configuration; plain HTTP is for loopback only, elsewhere TLS is required."""
    check_realm(setup.realm)
    host, _ = parse_listen(setup.listen)
    if (setup.tls_cert is None) != (setup.tls_key is None):
        raise ConfigProblem("--tls-cert and --tls-key go together: give both or neither")
    if setup.tls_cert is None and not is_loopback(host):
        raise ConfigProblem(
            f"--listen {setup.listen} is not a loopback address: give --tls-cert and --tls-key"
            " (plain HTTP would carry tokens and images in clear)"
        )
    http: dict[str, Any] = {
        "addr": setup.listen,
        # Instances behind one name must share it (it signs upload state); one per config otherwise.
        "secret": setup.http_secret,
        "headers": {"X-Content-Type-Options": ["nosniff"]},
    }
    if setup.tls_cert is not None and setup.tls_key is not None:
        http["tls"] = {"certificate": str(setup.tls_cert), "key": str(setup.tls_key)}
    config: dict[str, Any] = {
        "version": "0.1",
        "log": {"level": "info", "formatter": "text", "fields": {"service": "registry"}},
        "storage": {
            "filesystem": {"rootdirectory": str(setup.storage)},
            "cache": {"blobdescriptor": "inmemory"},
        },
        "http": http,
        "auth": {
            "token": {
                "realm": setup.realm,
                "service": setup.service,
                "issuer": setup.issuer,
                "rootcertbundle": str(setup.rootcertbundle),
            }
        },
    }
    if setup.notify_url:
        check_realm(setup.notify_url)
        config["notifications"] = {
            "endpoints": [
                {
                    "name": "bridgeos-cloud",
                    "url": setup.notify_url,
                    "headers": {"Authorization": [f"Bearer {setup.notify_token}"]},
                    "timeout": "5s",
                    "backoff": "2s",
                    # Layers are told too; only manifests (tags) are kept.
                    "ignoredmediatypes": ["application/octet-stream"],
                }
            ]
        }
    return config


def render_yaml(value: Any, indent: int = 0) -> str:
    """Write nested dicts, lists and strings as block YAML; every scalar is a JSON string, which YAML reads as is."""
    pad = "  " * indent
    lines = []
    for key, item in value.items():
        if isinstance(item, dict):
            lines.append(f"{pad}{key}:\n{render_yaml(item, indent + 1)}")
        elif isinstance(item, list) and item and all(isinstance(one, dict) for one in item):
            lines.append(f"{pad}{key}:")
            for one in item:
                block = render_yaml(one, indent + 2).split("\n")
                lines.append(f"{pad}  - {block[0].lstrip()}")
                lines.extend(block[1:])
        elif isinstance(item, list):
            lines.append(f"{pad}{key}: [{', '.join(json.dumps(str(one)) for one in item)}]")
        else:
            lines.append(f"{pad}{key}: {json.dumps(str(item))}")
    return "\n".join(lines)
