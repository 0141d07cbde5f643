"""The robot door's database threads: robots' reports applied side by side, each robot's in order, each once."""

from __future__ import annotations

import functools
from collections.abc import Awaitable, Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any

from channels.db import database_sync_to_async
from django.conf import settings
from django.db import connection, transaction
from django.utils import timezone

from monitoring.models import IngestedFrame

_REPORT_THREADS: ThreadPoolExecutor | None = None
# The acked frame whose handler is running: its database work claims the frame's id as it commits.
_APPLYING: ContextVar[tuple[str, str] | None] = ContextVar("applying_frame", default=None)
_CLAIM_SQL = (
    # Plain SQL both PostgreSQL and SQLite (make run's) take; the time from Python, not the SQL dialect.
    f"INSERT INTO {IngestedFrame._meta.db_table} (robot_id, frame_id, created) VALUES (%s, %s, %s) "
    "ON CONFLICT DO NOTHING RETURNING 1"
)


class AlreadyApplied(Exception):
    """An earlier copy of this frame was applied and committed: the robot resent it, unacked."""


def _report_threads() -> ThreadPoolExecutor:
    global _REPORT_THREADS
    if _REPORT_THREADS is None:
        _REPORT_THREADS = ThreadPoolExecutor(
            max_workers=settings.BRIDGEOS_ROBOT_DB_THREADS, thread_name_prefix="robot-db"
        )
    return _REPORT_THREADS


@contextmanager
def applying(robot_id: str, frame_id: str) -> Iterator[None]:
    """Have the database work of one acked frame's handler apply it at most once."""
    token = _APPLYING.set((robot_id, frame_id))
    try:
        yield
    finally:
        _APPLYING.reset(token)


def sync(function: Callable[..., Any]) -> Callable[..., Awaitable[Any]]:
    """Run a handler's database work on the robot door's threads.

    A robot's frames are still applied one after the other (its consumer awaits each), but different
    robots' reports no longer queue behind each other in the one thread Django gives async code:
    their round trips to PostgreSQL overlap. A rollout's 1,000 robots report 8,000 statuses in a minute.
    Within `applying`, the work commits together with the frame's id, or raises AlreadyApplied.
    """
    frame = _APPLYING.get()
    if frame is not None:
        function = functools.partial(_once, frame, function)
    return database_sync_to_async(function, thread_sensitive=False, executor=_report_threads())


def _once(frame: tuple[str, str], function: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
    # The Redis window of applied ids is saved every few seconds: a daphne killed in between would
    # let a resent copy through. The id committed with the frame's effects closes that gap.
    with transaction.atomic():
        with connection.cursor() as cursor:
            cursor.execute(_CLAIM_SQL, [*frame, timezone.now()])
            if cursor.fetchone() is None:
                raise AlreadyApplied(frame[1])
        return function(*args, **kwargs)
