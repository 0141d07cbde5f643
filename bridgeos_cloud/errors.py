"""Domain errors that every door (REST, WebSocket, CLI) turns into a clear answer."""

from __future__ import annotations


class NotFound(LookupError):
    """A robot, skill or component named in a request does not exist (or is not yours)."""

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field
