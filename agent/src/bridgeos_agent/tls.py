"""Decide how the agent trusts the cloud: TLS contexts, and where plain ws:// may go."""

from __future__ import annotations

import ipaddress
import ssl
from pathlib import Path
from urllib.parse import urlsplit, urlunsplit

__all__ = ["InsecureMaster", "check_master_url", "client_context", "http_base", "is_loopback"]


class InsecureMaster(ValueError):
    """A plain ws:// URL points away from this machine without an explicit permission."""


def is_loopback(host: str) -> bool:
    """Tell whether a host name or address stays on this machine."""
    host = host.strip("[]").lower()
    if host == "localhost" or host.endswith(".localhost"):
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def check_master_url(url: str, *, allow_insecure: bool = False) -> None:
    """Refuse a plain ws:// URL to another machine unless explicitly allowed: the token would travel in clear."""
    parts = urlsplit(url)
    if parts.scheme == "ws" and not allow_insecure and not is_loopback(parts.hostname or ""):
        raise InsecureMaster(
            f"{url} is not encrypted and leaves this machine: use wss:// (the cloud serves TLS, see the README), "
            "or pass --allow-insecure (env BRIDGEOS_ALLOW_INSECURE=1) on a network you trust"
        )


def client_context(*, ca_file: Path | None = None, ca_pem: str | None = None) -> ssl.SSLContext:
    """Build the context that verifies the cloud: a --ca file, else a CA pinned by the cloud, else the system's CAs."""
    context = ssl.create_default_context(ssl.Purpose.SERVER_AUTH)
    if ca_file is not None or ca_pem:
        # Only the named CA: a pinned cloud is not trusted on the word of any public CA.
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
        if ca_file is not None:
            context.load_verify_locations(cafile=str(ca_file))
        else:
            context.load_verify_locations(cadata=ca_pem)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    context.check_hostname = True
    context.verify_mode = ssl.CERT_REQUIRED
    return context


def http_base(master: str) -> str:
    """Return the cloud's HTTP(S) base URL for a ws:// or wss:// master URL."""
    parts = urlsplit(master)
    scheme = "https" if parts.scheme == "wss" else "http"
    return urlunsplit((scheme, parts.netloc, "", "", "")).rstrip("/")
