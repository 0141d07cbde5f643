"""The log table's time partitions on PostgreSQL: one per UTC day, created ahead, dropped whole when expired.

The same scheme as the metric table's (`monitoring.partitions`, whose pure day helpers this
reuses): a partition `logs_componentlog_pYYYYMMDD` per day, a default partition for any line no
day covers (a robot clock far off), and retention by dropping whole days. The primary key is
(id, ts) and the line's key (robot, skill, component, location, seq, ts) is unique, both holding
the partition key as PostgreSQL requires. The embedded SQLite default keeps a plain table.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from datetime import date, datetime, timedelta
from typing import Any

from django.db import connection as default_connection
from django.db import transaction
from django.utils import timezone

from monitoring.partitions import day_of, day_start, days_between, expired_days

TABLE = "logs_componentlog"
DEFAULT_PARTITION = f"{TABLE}_default"
PARTITION_PATTERN = re.compile(rf"^{TABLE}_p(\d{{8}})$")
# Logs are kept days, not months: two days ahead is plenty with the hourly task and the default partition.
AHEAD_DAYS = 2


def partition_name(day: date) -> str:
    """Return the name of the partition holding a UTC day."""
    return f"{TABLE}_p{day:%Y%m%d}"


def is_partitioned(connection: Any = default_connection) -> bool:
    """Tell whether the log table is a partitioned table here."""
    if connection.vendor != "postgresql":
        return False
    with connection.cursor() as cursor:
        cursor.execute("SELECT relkind FROM pg_class WHERE oid = to_regclass(%s)", [TABLE])
        row = cursor.fetchone()
    return row is not None and row[0] == "p"


def _locked_and_absent(cursor: Any, name: str) -> bool:
    """Take this transaction's lock on the log table's partition maintenance; tell whether the partition is missing."""
    cursor.execute("SELECT pg_advisory_xact_lock(hashtext(%s))", [TABLE])
    cursor.execute(
        "SELECT NOT EXISTS (SELECT FROM pg_class c JOIN pg_namespace n ON n.oid = c.relnamespace"
        " WHERE c.relname = %s AND n.nspname = current_schema())",
        [name],
    )
    return cursor.fetchone()[0]


def partition_days(connection: Any = default_connection) -> list[date]:
    """Return the days that have a partition, oldest first."""
    with connection.cursor() as cursor:
        cursor.execute(
            "SELECT c.relname FROM pg_inherits i JOIN pg_class c ON c.oid = i.inhrelid"
            " WHERE i.inhparent = to_regclass(%s)",
            [TABLE],
        )
        names = [row[0] for row in cursor.fetchall()]
    days = []
    for name in names:
        match = PARTITION_PATTERN.match(name)
        if match:
            digits = match.group(1)
            days.append(date(int(digits[:4]), int(digits[4:6]), int(digits[6:])))
    return sorted(days)


def create_partitions(days: Iterable[date], connection: Any = default_connection) -> list[date]:
    """Create the partitions of these days that are missing; return the days created."""
    existing = set(partition_days(connection))
    created = []
    for day in sorted(set(days) - existing):
        name, start, end = partition_name(day), day_start(day), day_start(day + timedelta(days=1))
        with transaction.atomic(using=connection.alias), connection.cursor() as cursor:
            if not _locked_and_absent(cursor, name):
                continue  # another process created it meanwhile
            # Lines of this day sitting in the default partition would make the new partition fail:
            # build it beside the table, move them in, then attach it (as the metric table does).
            cursor.execute(f"CREATE TABLE {name} (LIKE {TABLE} INCLUDING DEFAULTS)")
            cursor.execute(
                f"WITH moved AS (DELETE FROM {DEFAULT_PARTITION} WHERE ts >= %s AND ts < %s RETURNING *)"
                f" INSERT INTO {name} SELECT * FROM moved",
                [start, end],
            )
            cursor.execute(
                f"ALTER TABLE {name} ADD CONSTRAINT {name}_bounds CHECK (ts >= %s AND ts < %s)", [start, end]
            )
            cursor.execute(f"ALTER TABLE {TABLE} ATTACH PARTITION {name} FOR VALUES FROM (%s) TO (%s)", [start, end])
            cursor.execute(f"ALTER TABLE {name} DROP CONSTRAINT {name}_bounds")
        created.append(day)
    return created


def ensure_partitions(now: datetime | None = None, connection: Any = default_connection) -> list[date]:
    """Create the partitions of yesterday, today and the days ahead that are missing; return those created."""
    if not is_partitioned(connection):
        return []
    today = day_of(now or timezone.now())
    return create_partitions(days_between(today - timedelta(days=1), today + timedelta(days=AHEAD_DAYS)), connection)


def drop_expired_partitions(cutoff: datetime, connection: Any = default_connection) -> int:
    """Drop every day partition wholly before the cutoff; return how many lines went with them."""
    dropped = 0
    for day in expired_days(partition_days(connection), cutoff):
        name = partition_name(day)
        with transaction.atomic(using=connection.alias), connection.cursor() as cursor:
            if _locked_and_absent(cursor, name):
                continue  # another process dropped it meanwhile
            cursor.execute(f"LOCK TABLE {name} IN ACCESS EXCLUSIVE MODE")
            cursor.execute(f"SELECT count(*) FROM {name}")
            dropped += cursor.fetchone()[0]
            cursor.execute(f"DROP TABLE {name}")
    return dropped
