"""The flush between tests empties every table, the append-only audit log and a write in flight included.

Real PostgreSQL, the flush that pytest-django runs after each transactional test (tests/fastflush.py).
"""

from __future__ import annotations

import threading
import time
from datetime import UTC, datetime

import pytest
from django.apps import apps
from django.contrib.auth import get_user_model
from django.core.management.color import no_style
from django.db import connection

from audit.models import AuditEntry
from audit.services import record as audit
from monitoring.models import Event, Metric
from monitoring.services import record_event
from robots.services import create_robot
from tests.inflight import write_in_flight

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(60)]


def flush() -> None:
    """Empty every model's table as pytest-django does between tests."""
    tables = connection.introspection.django_table_names(only_existing=True, include_views=False)
    connection.ops.execute_sql_flush(connection.ops.sql_flush(no_style(), tables))


def rows() -> dict[str, int]:
    """Every model's row count, by label."""
    return {model._meta.label: model.objects.count() for model in apps.get_models() if model._meta.managed}


def test_the_flush_deletes_instead_of_truncating_and_empties_every_table():
    assert not any(sql.startswith("TRUNCATE") for sql in connection.ops.sql_flush(no_style(), ["robots_robot"]))
    create_robot("flushed-1", get_user_model().objects.create_user("flush-owner"))
    Metric.objects.create(robot_id="flushed-1", name="cpu", value=1.0, ts=datetime.now(UTC))
    record_event("before the flush", robot_id="flushed-1", kind="test")
    audit("robot.create", door="system", target="flushed-1")
    assert AuditEntry.objects.exists()  # a table whose triggers refuse DELETE

    flush()

    assert {label: n for label, n in rows().items() if n} == {}


def test_a_write_in_flight_is_waited_for_and_emptied_too():
    def write(started: threading.Event) -> None:
        record_event("written while the tables are flushed", kind="test")
        started.set()
        time.sleep(0.5)  # the flush is waiting for the event log's lock by now

    with write_in_flight(write) as writer_errors:
        flush()

    assert writer_errors == []  # the write committed, and then the flush emptied it
    assert not Event.objects.exists()  # a plain DELETE would not have seen the row not yet committed
