"""Turn the agent package's pydantic config errors into Django field errors."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from django.core.exceptions import ValidationError
from pydantic import BaseModel
from pydantic import ValidationError as PydanticValidationError

from bridgeos_agent.errors import field_errors


def validated_config(parse: Callable[[Any], BaseModel], data: Any, field: str = "config") -> dict[str, Any]:
    """Return the config normalised by its schema, or raise field errors naming each bad path."""
    try:
        model = parse(data)
    except PydanticValidationError as exc:
        messages = [
            f"{path}: {message}" if path and path != "__all__" else message
            for path, path_messages in field_errors(exc).items()
            for message in path_messages
        ]
        raise ValidationError({field: messages}, code="invalid_config") from None
    return model.model_dump(mode="json")
