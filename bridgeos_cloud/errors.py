"""Domain errors that every door (REST, WebSocket, CLI) turns into a clear answer."""

from __future__ import annotations

from typing import Any

from django.conf import settings
from django.core.exceptions import RequestDataTooBig
from rest_framework.response import Response
from rest_framework.views import exception_handler


class NotFound(LookupError):
    """A robot, skill or component named in a request does not exist (or is not yours)."""

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field


def api_exception_handler(exc: Exception, context: dict[str, Any]) -> Response | None:
    """Answer DRF's way, and an oversize body with 413 rather than Django's generic 400."""
    if isinstance(exc, RequestDataTooBig):
        limit = settings.DATA_UPLOAD_MAX_MEMORY_SIZE
        return Response({"detail": f"Request body too large: the limit is {limit} bytes."}, status=413)
    return exception_handler(exc, context)
