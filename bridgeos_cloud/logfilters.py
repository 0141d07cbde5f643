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


class ClientFaultAsWarning(logging.Filter):
    """Log a request Django refused as suspicious (answered 400) as a one-line warning, not an error.

    Django logs every SuspiciousOperation (too many fields, a disallowed host, a body too big) on
    ``django.security.<name>`` at ERROR with its traceback: a client's bad request, answered with a
    clear 400, not a fault of the cloud. Set on the handler, since a filter on the ``django.security``
    logger would never see its children's records.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        if record.name.startswith("django.security.") and record.levelno > logging.WARNING:
            record.levelno, record.levelname = logging.WARNING, "WARNING"
            record.exc_info, record.exc_text = None, None
        return True
