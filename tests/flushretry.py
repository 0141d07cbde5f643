"""Retry the tables' flush between tests when PostgreSQL picks it as a deadlock's victim.

pytest-django empties the tables with one TRUNCATE, which takes them one by one in an order of
its own. A cloud process that is still finishing a write when a test ends (an ingest batch, a
worker's report, a presence sweep) locks a robot's row and then the table it writes to, and may
meet the TRUNCATE the other way round: PostgreSQL aborts one of the two. Tests quiet the servers
they know of first, but a batch already on its way cannot be called back. When the flush is the
one aborted, the write commits and the flush, retried, finds nothing in its way, as PostgreSQL's
manual advises for a deadlock. A deadlock between two of the cloud's own transactions is not
retried here: only the flush is.
"""

from __future__ import annotations

import time
from typing import Any

ATTEMPTS = 5
PAUSE_S = 0.2


def retry_flush_deadlocks() -> None:
    """Make Django's flush retry a TRUNCATE that PostgreSQL aborted as a deadlock's victim."""
    from django.db import OperationalError
    from django.db.backends.base.operations import BaseDatabaseOperations

    flush = BaseDatabaseOperations.execute_sql_flush
    if getattr(flush, "retries_deadlocks", False):
        return

    def execute_sql_flush(self: Any, sql_list: list[str]) -> None:
        for attempt in range(1, ATTEMPTS + 1):
            try:
                return flush(self, sql_list)
            except OperationalError as exc:
                if not is_deadlock(exc) or attempt == ATTEMPTS:
                    raise
                time.sleep(PAUSE_S)

    execute_sql_flush.retries_deadlocks = True  # type: ignore[attr-defined]
    BaseDatabaseOperations.execute_sql_flush = execute_sql_flush  # type: ignore[method-assign]


def is_deadlock(exc: BaseException) -> bool:
    """Tell whether a database error is PostgreSQL's "deadlock detected" (SQLSTATE 40P01)."""
    cause = exc.__cause__
    return getattr(cause, "sqlstate", None) == "40P01"
