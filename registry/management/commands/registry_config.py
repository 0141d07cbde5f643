"""Write a Distribution registry's config.yml and token certificate, pointed at this cloud's token endpoint."""

from __future__ import annotations

import os
import secrets
import tempfile
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from django.conf import settings
from django.core.management.base import BaseCommand, CommandError, CommandParser
from django.utils import timezone

from bridgeos_cloud.env import ConfigError
from network import pki
from registry import services, tokens
from registry.config import ConfigProblem, RegistrySetup, render_config, render_yaml


class Command(BaseCommand):
    help = (
        "Write OUT/config.yml and OUT/token.crt so `docker-registry serve OUT/config.yml` trusts this cloud's tokens."
    )

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument(
            "--realm", required=True, help="The token endpoint's URL, e.g. http://HOST/api/registry/token"
        )
        parser.add_argument("--listen", required=True, help="HOST:PORT the registry listens on")
        parser.add_argument("--storage", required=True, help="Directory the registry keeps images in")
        parser.add_argument("--out", required=True, help="Directory to write config.yml and token.crt into")
        parser.add_argument("--service", default=settings.BRIDGEOS["REGISTRY_SERVICE"], help="The tokens' audience")
        parser.add_argument("--issuer", default=settings.BRIDGEOS["REGISTRY_ISSUER"], help="The tokens' issuer")
        parser.add_argument("--tls-cert", help="PEM certificate to serve HTTPS with (required off loopback)")
        parser.add_argument("--tls-key", help="PEM key of --tls-cert")
        parser.add_argument(
            "--notify",
            help="Where the registry tells the cloud of pushes (default: the realm's /api/registry/events; off: not)",
        )

    def handle(self, *args: Any, **options: Any) -> None:
        out = Path(options["out"]).resolve()
        tls = [Path(options[name]).resolve() if options[name] else None for name in ("tls_cert", "tls_key")]
        for path in tls:
            if path is not None and not path.is_file():
                raise CommandError(f"{path} does not exist or is not a file")
        if out.exists() and not out.is_dir():
            raise CommandError(f"--out {out} exists and is not a directory")
        if not options["service"] or not options["issuer"]:
            raise CommandError("--service and --issuer must not be empty")
        setup = RegistrySetup(
            realm=options["realm"],
            listen=options["listen"],
            storage=Path(options["storage"]).resolve(),
            rootcertbundle=out / "token.crt",
            service=options["service"],
            issuer=options["issuer"],
            http_secret=secrets.token_urlsafe(32),
            tls_cert=tls[0],
            tls_key=tls[1],
            notify_url=_notify_url(options["realm"], options["notify"]),
            notify_token=services.notify_token(),
        )
        try:
            config = render_yaml(render_config(setup)) + "\n"
        except ConfigProblem as exc:
            raise CommandError(str(exc)) from None
        try:
            key = services.signing_key()
        except ConfigError as exc:
            raise CommandError(str(exc)) from None
        cert = tokens.signing_certificate(key, common_name="bridgeOS registry tokens", now=timezone.now())
        out.mkdir(parents=True, exist_ok=True)
        _write(out / "token.crt", pki.pem(cert), 0o644)
        # Last, so a config.yml that exists always names a certificate that does. Not world-readable: its
        # http secret signs upload state.
        _write(out / "config.yml", config, 0o640)
        self.stdout.write(
            f"Wrote {out / 'config.yml'} and {out / 'token.crt'} (key id {tokens.key_id(key.public_key())});"
            f" run: docker-registry serve {out / 'config.yml'}"
        )


def _notify_url(realm: str, notify: str | None) -> str | None:
    """Return the notifications URL: the one given, none for 'off', else the realm's sibling /api/registry/events."""
    if notify == "off":
        return None
    if notify:
        return notify
    parts = urlsplit(realm)
    return f"{parts.scheme}://{parts.netloc}/api/registry/events"


def _write(path: Path, text: str, mode: int) -> None:
    """Replace a file whole: a registry starting meanwhile reads the old one or the new one, never half."""
    fd, draft = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    with os.fdopen(fd, "w") as out:
        out.write(text)
    os.chmod(draft, mode)
    os.replace(draft, path)
