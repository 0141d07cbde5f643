"""Log a failure that repeats every tick once per distinct error, not once per tick."""

from __future__ import annotations

import logging

__all__ = ["LogOnce"]


class LogOnce:
    """Say each distinct error of one recurring action once, and say when the action works again."""

    def __init__(self, logger: logging.Logger, action: str, *, traceback: bool = False) -> None:
        self.logger = logger
        self.action = action
        self.traceback = traceback  # an unexpected error of a loop: keep where it came from
        self._said: set[str] = set()

    def failed(self, exc: BaseException) -> bool:
        """Log ``exc`` unless the same error was logged since the action last worked; return whether logged."""
        key = f"{type(exc).__name__}: {exc}"
        if key in self._said:
            return False
        # Bounded: an error text that changes every time (a counter in it) must not grow the set forever.
        if len(self._said) >= 100:
            self._said.clear()
        self._said.add(key)
        self.logger.warning(
            "%s failed: %s (said once until it works again)", self.action, key, exc_info=exc if self.traceback else None
        )
        return True

    def worked(self) -> None:
        """Note that the action worked, so its next failure is logged again."""
        if self._said:
            self._said.clear()
            self.logger.info("%s works again", self.action)
