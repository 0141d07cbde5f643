"""The command groups of `bridgeos`, one module per area of the Robot API."""

from __future__ import annotations

import re
from datetime import UTC, datetime, timedelta

import click

SLUG = re.compile(r"^[a-z0-9][a-z0-9_-]{0,63}$")
DURATION = re.compile(r"^(\d+(?:\.\d+)?)([smhdw])$")
UNIT_S = {"s": 1, "m": 60, "h": 3600, "d": 86400, "w": 604800}


def split_path(path: str, *, least: int, most: int, what: str = "ROBOT[/SKILL[/COMPONENT]]") -> list[str]:
    """Split ROBOT/SKILL/COMPONENT into its parts, at least ``least`` and at most ``most``."""
    parts = path.strip("/").split("/")
    if not least <= len(parts) <= most or not all(parts):
        raise click.UsageError(f"{path!r}: expected {what}.")
    return parts


def when(value: str | None, option: str) -> str | None:
    """Return an ISO 8601 UTC time for --since/--until: a time as given, or `10m`, `2h`, `1d` ago."""
    if value is None:
        return None
    found = DURATION.match(value.strip())
    if found:
        ago = timedelta(seconds=float(found.group(1)) * UNIT_S[found.group(2)])
        return (datetime.now(UTC) - ago).isoformat().replace("+00:00", "Z")
    try:
        float(value)
        return value  # unix seconds, as the logs API takes them too
    except ValueError:
        pass
    try:
        datetime.fromisoformat(value.replace("Z", "+00:00"))
    except ValueError:
        raise click.BadParameter(
            "an ISO 8601 time (2026-12-04T19:00:00Z), unix seconds, or a duration ago (30s, 10m, 2h, 1d)",
            param_hint=option,
        ) from None
    return value


def load_json_file(path: str, option: str) -> object:
    """Read a JSON file (`-` for stdin), or fail naming the option."""
    import json

    try:
        text = click.open_file(path).read()
    except OSError as exc:
        raise click.BadParameter(str(exc), param_hint=option) from None
    try:
        return json.loads(text)
    except ValueError as exc:
        raise click.BadParameter(f"not JSON: {exc}", param_hint=option) from None


def url_path(*parts: str) -> str:
    """Join path segments for a URL, each quoted: a robot id never reaches another route."""
    from urllib.parse import quote

    return "/".join(quote(part, safe="") for part in parts)
