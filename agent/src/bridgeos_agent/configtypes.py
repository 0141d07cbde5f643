"""The field types, patterns and validation helpers the Skill configuration is made of."""

from __future__ import annotations

import shlex
from collections.abc import Sequence
from typing import Annotated, Any, Literal

from pydantic import BaseModel, BeforeValidator, ConfigDict, Field, StringConstraints, WithJsonSchema
from pydantic_core import PydanticCustomError

__all__ = [
    "ENV_NAME_PATTERN",
    "HTTP_PREFIX_PATTERN",
    "IDENTIFIER_PATTERN",
    "IMAGE_PATTERN",
    "JSON_SCHEMA_DIALECT",
    "MAX_COST_FUNCTION_LENGTH",
    "PLACEMENT_PATTERN",
    "ROS_NAME_PATTERN",
    "ROS_TYPE_PATTERN",
    "SLUG_PATTERN",
    "VOLUME_PATTERN",
    "Activation",
    "Command",
    "EnvName",
    "FiniteFloat",
    "HttpMethod",
    "Identifier",
    "Issue",
    "Location",
    "NonNegative",
    "PlacementConstraint",
    "Policy",
    "Port",
    "RosName",
    "RosType",
    "Slug",
    "StrictModel",
    "VolumeName",
    "config_issues",
    "raise_issues",
    "reject_duplicates",
]

JSON_SCHEMA_DIALECT = "https://json-schema.org/draft/2020-12/schema"

# Ids end up in URLs, container names, ROS namespaces and env values, so keep them plain.
SLUG_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,63}$"
# Docker rejects volume names outside this pattern (moby's RestrictedNamePattern).
VOLUME_PATTERN = r"^[a-zA-Z0-9][a-zA-Z0-9_.-]{1,127}$"
# Absolute or relative ROS graph names; "~" (private) names are refused because the
# router resolves them in its own namespace, not the component's.
ROS_NAME_PATTERN = r"^/?[A-Za-z][A-Za-z0-9_]*(/[A-Za-z][A-Za-z0-9_]*)*$"
# ROS 1 spells a type 'package/Type'; ROS 2 also 'package/msg/Type' (srv, action).
ROS_TYPE_PATTERN = r"^[A-Za-z][A-Za-z0-9_]*/((msg|srv|action)/)?[A-Za-z][A-Za-z0-9_]*$"
IDENTIFIER_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]{0,63}$"
ENV_NAME_PATTERN = r"^[A-Za-z_][A-Za-z0-9_]*$"
HTTP_PREFIX_PATTERN = r"^/[A-Za-z0-9._~!$&'()*+,;=:@%/-]*$"
IMAGE_PATTERN = r"^[^\s]{1,255}$"
# Docker Swarm's constraint syntax: an attribute, == or !=, a value.
PLACEMENT_PATTERN = r"^[A-Za-z][A-Za-z0-9_.-]{0,127} ?(==|!=) ?[^\s]{1,128}$"

Slug = Annotated[str, StringConstraints(pattern=SLUG_PATTERN)]
VolumeName = Annotated[str, StringConstraints(pattern=VOLUME_PATTERN)]
RosName = Annotated[str, StringConstraints(pattern=ROS_NAME_PATTERN, max_length=256)]
RosType = Annotated[str, StringConstraints(pattern=ROS_TYPE_PATTERN, max_length=256)]
Identifier = Annotated[str, StringConstraints(pattern=IDENTIFIER_PATTERN)]
EnvName = Annotated[str, StringConstraints(pattern=ENV_NAME_PATTERN, max_length=256)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Port = Annotated[int, Field(ge=1, le=65535)]
PlacementConstraint = Annotated[str, StringConstraints(pattern=PLACEMENT_PATTERN)]

Location = Literal["robot", "cloud", "either"]
Policy = Literal["energy", "network", "monetary", "performance", "custom"]
Activation = Literal["relu", "tanh", "sigmoid"]
HttpMethod = Literal["GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"]

MAX_COST_FUNCTION_LENGTH = 2000

Issue = tuple[tuple[str | int, ...], str]


def _split_command(value: Any) -> Any:
    """Split a command given as one string the way a shell would, without a shell."""
    if isinstance(value, str):
        try:
            return shlex.split(value)
        except ValueError as exc:
            raise ValueError(f"cannot split command string: {exc}") from None
    return value


Command = Annotated[
    list[str],
    BeforeValidator(_split_command),
    WithJsonSchema(
        {
            "anyOf": [
                {"type": "array", "items": {"type": "string"}},
                {"type": "string"},
            ],
            "description": "Argument vector, or one string split like a shell would.",
        },
        mode="validation",
    ),
]


def reject_duplicates(values: Sequence[Any], what: str) -> None:
    """Reject a sequence that holds the same value twice."""
    seen: set[Any] = set()
    for value in values:
        if value in seen:
            raise ValueError(f"duplicate {what} {value!r}")
        seen.add(value)


def raise_issues(issues: list[Issue]) -> None:
    """Raise one error carrying every cross-field issue with its own relative path."""
    if issues:
        summary = "; ".join(f"{'.'.join(str(p) for p in path)}: {msg}" if path else msg for path, msg in issues)
        raise PydanticCustomError(
            "skill_config",
            "{summary}",
            {"summary": summary, "issues": tuple(issues)},
        )


def config_issues(ctx: dict[str, Any] | None) -> list[Issue]:
    """Return the per-path issues a cross-field validator attached to an error's ctx."""
    if not ctx:
        return []
    issues = ctx.get("issues") or ()
    return [(tuple(path), str(msg)) for path, msg in issues]


class StrictModel(BaseModel):
    """Reject unknown fields so typos surface as errors instead of silent defaults."""

    model_config = ConfigDict(extra="forbid", str_strip_whitespace=False)
