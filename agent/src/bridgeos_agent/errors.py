"""Turn pydantic validation errors into field-level messages for people."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import pydantic

from bridgeos_agent import skillconfig

__all__ = ["NON_FIELD", "field_errors"]

NON_FIELD = "__all__"

# Regexes mean little to the people fixing a config, so say what each pattern wants.
PATTERN_HINTS: dict[str, str] = {
    skillconfig.SLUG_PATTERN: ("use 1-64 lowercase letters, digits, '-' or '_', starting with a letter or digit"),
    skillconfig.VOLUME_PATTERN: (
        "use a Docker volume name: 2-128 letters, digits, '_', '.' or '-', starting with a letter or digit"
    ),
    skillconfig.ROS_NAME_PATTERN: (
        "use a ROS graph name such as '/camera/points': segments of letters, digits "
        "and '_', each starting with a letter"
    ),
    skillconfig.ROS_TYPE_PATTERN: "use a ROS type such as 'sensor_msgs/PointCloud2'",
    skillconfig.IDENTIFIER_PATTERN: ("use an identifier: letters, digits and '_', not starting with a digit"),
    skillconfig.ENV_NAME_PATTERN: (
        "use an environment variable name: letters, digits and '_', not starting with a digit"
    ),
    skillconfig.HTTP_PREFIX_PATTERN: "use a URL path starting with '/'",
    skillconfig.IMAGE_PATTERN: "use a Docker image reference without whitespace",
}


def _dotted(loc: Sequence[str | int]) -> str:
    """Join an error location into a dotted path, or name it non-field."""
    return ".".join(str(part) for part in loc) or NON_FIELD


def _message(error: Mapping[str, Any], loc: tuple[str | int, ...]) -> str:
    """Phrase one pydantic error for a person fixing a configuration."""
    kind = error.get("type")
    if kind == "extra_forbidden" and loc:
        return f"unknown field {loc[-1]!r}"
    if kind == "missing":
        return "this field is required"
    if kind == "string_pattern_mismatch":
        ctx = error.get("ctx")
        pattern = ctx.get("pattern") if isinstance(ctx, dict) else None
        if isinstance(pattern, str) and pattern in PATTERN_HINTS:
            return PATTERN_HINTS[pattern]
    if kind == "value_error":
        return str(error.get("msg", "invalid value")).removeprefix("Value error, ")
    return str(error.get("msg", "invalid value"))


def field_errors(exc: pydantic.ValidationError) -> dict[str, list[str]]:
    """Map dotted field paths (e.g. components.detector.resources.cpu) to messages."""
    result: dict[str, list[str]] = {}
    for error in exc.errors(include_url=False):
        loc = tuple(error.get("loc", ()))
        key_error = bool(loc) and loc[-1] == "[key]"
        if key_error:
            # A bad dict key (e.g. a component id) belongs to the key itself.
            loc = loc[:-1]
        ctx = error.get("ctx") or {}
        issues = ctx.get("issues") if isinstance(ctx, dict) else None
        if issues:
            # Cross-field validators attach each issue's path relative to their model.
            for path, message in issues:
                result.setdefault(_dotted((*loc, *path)), []).append(str(message))
            continue
        message = _message(error, loc)
        if key_error:
            message = f"invalid key: {message}"
        result.setdefault(_dotted(loc), []).append(message)
    return result
