"""Filters of the cloud's log records."""

from __future__ import annotations

import logging

# Answers that say a robot is offline (503) or did not answer in time (504): the state of a robot, not
# a fault of the cloud, so they are warnings in the log; Django would log every 5xx as an error.
ROBOT_STATUSES = frozenset({503, 504})


class RobotStateAsWarning(logging.Filter):
    """Log a request answered 503 or 504 (a robot offline or late) as a warning, not an error."""

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "status_code", None) in ROBOT_STATUSES and record.levelno > logging.WARNING:
            record.levelno, record.levelname = logging.WARNING, "WARNING"
        return True
