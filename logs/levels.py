"""Tell the level a line of output says, when it says one: ROS's [INFO], Python logging, JSON lines."""

from __future__ import annotations

import json
import re

_NAMES = {
    "debug": "debug",
    "info": "info",
    "warn": "warning",
    "warning": "warning",
    "error": "error",
    "err": "error",
    "fatal": "critical",
    "critical": "critical",
}
# "[INFO] ...", "[ WARN] [1700000000.1]: ..." (ROS), "WARNING:root:..." and "... ERROR name: ..." (Python logging).
_BRACKETED = re.compile(r"^\s*\[\s*(DEBUG|INFO|WARN|WARNING|ERROR|FATAL|CRITICAL)\s*\]", re.IGNORECASE)
_WORD = re.compile(r"(?:^|\s)(DEBUG|INFO|WARNING|WARN|ERROR|CRITICAL|FATAL)(?::|\s)")


def parse_level(text: str) -> str | None:
    """Return the level a line says (debug, info, warning, error, critical), or None."""
    match = _BRACKETED.match(text)
    if match:
        return _NAMES[match.group(1).lower()]
    if text.startswith("{"):
        try:
            record = json.loads(text)
        except ValueError:
            record = None
        if isinstance(record, dict):
            value = record.get("level") or record.get("levelname") or record.get("severity")
            return _NAMES.get(value.lower()) if isinstance(value, str) else None
    match = _WORD.search(text[:200])
    return _NAMES[match.group(1).lower()] if match else None
