"""A write in flight on a connection of its own, for tests of what the flush between tests meets."""

from __future__ import annotations

import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from django.db import connection, transaction


@contextmanager
def write_in_flight(work: Callable[[threading.Event], None]) -> Iterator[list[BaseException]]:
    """Run ``work`` in a transaction on a thread of its own, enter once it sets the event, and join it on leaving.

    Yields the list the writer's errors land in (empty when it committed).
    """
    started = threading.Event()
    errors: list[BaseException] = []

    def writer() -> None:
        try:
            with transaction.atomic():
                work(started)
        except BaseException as exc:  # handed to the test
            errors.append(exc)
        finally:
            started.set()
            connection.close()

    thread = threading.Thread(target=writer)
    thread.start()
    assert started.wait(10)
    try:
        yield errors
    finally:
        thread.join(20)
