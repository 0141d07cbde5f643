"""Log the failures of a repeating loop once per distinct error, and its recovery, instead of every round."""

from __future__ import annotations

import logging


class RepeatedFailures:
    """Remember the last failure of a loop that runs every few seconds, so a lasting fault is logged once."""

    def __init__(self, logger: logging.Logger, what: str) -> None:
        self.logger = logger
        self.what = what
        self._last: str | None = None

    def failed(self, exc: BaseException) -> None:
        """Log a failure with its traceback unless it is the same as the previous round's."""
        key = f"{type(exc).__name__}: {exc}"
        if key != self._last:
            self.logger.error("%s failed (logged once until it changes or recovers)", self.what, exc_info=exc)
            self._last = key

    def succeeded(self) -> None:
        """Note a round that worked: say so once after failures, and log the next failure again."""
        if self._last is not None:
            self.logger.info("%s works again", self.what)
            self._last = None
