"""The flush between tests retries a TRUNCATE that PostgreSQL aborted as a deadlock's victim.

Real PostgreSQL, two connections: a writer holds a robot's row and then writes an event, as an
ingest batch or a worker's report does, while the flush truncates the two tables the other way round.
"""

from __future__ import annotations

import threading
import time

import pytest
from django.contrib.auth import get_user_model
from django.db import OperationalError, connection

from monitoring.models import Event
from monitoring.services import record_event
from robots.models import Robot
from robots.services import create_robot, hold_robot
from tests import flushretry
from tests.inflight import write_in_flight

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(60)]

# The event log first, then the robots: the order in which the writer below meets them reversed.
FLUSH = [f'TRUNCATE "{Event._meta.db_table}", "{Robot._meta.db_table}" CASCADE']


def flush_while_a_writer_holds_a_robot() -> tuple[BaseException | None, list[BaseException]]:
    """Flush while a writer holds a robot's row and then writes an event; return the flush's error and the writer's."""
    create_robot("flushed-1", get_user_model().objects.create_user("flush-owner"))

    def write(started: threading.Event) -> None:
        assert hold_robot("flushed-1")
        started.set()
        time.sleep(0.3)  # the flush has taken the event log by now, and waits for the robots
        record_event("written while the tables are flushed", robot_id="flushed-1", kind="test")

    error = None
    with write_in_flight(write) as writer_errors:
        try:
            connection.ops.execute_sql_flush(FLUSH)
        except OperationalError as exc:
            error = exc
    return error, writer_errors


def test_a_flush_that_loses_a_deadlock_to_a_writer_is_retried_and_empties_the_tables():
    error, writer_errors = flush_while_a_writer_holds_a_robot()

    assert error is None
    assert writer_errors == []  # the writer committed: the flush, not the cloud's write, gave way
    assert not Robot.objects.exists()
    assert not Event.objects.exists()


def test_without_the_retry_that_flush_fails_on_the_deadlock(monkeypatch):
    monkeypatch.setattr(flushretry, "ATTEMPTS", 1)

    error, writer_errors = flush_while_a_writer_holds_a_robot()

    assert error is not None and flushretry.is_deadlock(error), error
    assert writer_errors == []
