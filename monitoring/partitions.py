"""The metric table's time partitions on PostgreSQL: one per UTC day, created ahead, dropped whole when expired.

`monitoring_metric` is partitioned by range of `ts` (migration 0004). Each day has a partition
`monitoring_metric_pYYYYMMDD`; a default partition `monitoring_metric_default` takes any row no
day partition covers (a robot clock far off, a day not yet created), so an insert never fails for
lack of a partition. Creating a day whose rows already sit in the default partition moves them
into it first. Retention drops the partitions past the retention age instead of deleting their
rows. PostgreSQL requires the partition key in every unique index, so the primary key is
(id, ts); Django still sees `id` as the primary key, unique by its sequence.

The embedded SQLite default keeps a plain table: nothing here applies to it.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterable
from datetime import UTC, date, datetime, timedelta
from typing import Any

from django.conf import settings
from django.db import connection as default_connection
from django.db import transaction
from django.utils import timezone

TABLE = "monitoring_metric"


def day_of(ts: datetime) -> date:
    """Return the UTC day a time falls on."""
    return ts.astimezone(UTC).date()


def day_start(day: date) -> datetime:
    """Return the first instant of a UTC day."""
    return datetime(day.year, day.month, day.day, tzinfo=UTC)


def days_between(first: date, last: date) -> list[date]:
    """Return every day from first to last, both included."""
    return [first + timedelta(days=n) for n in range((last - first).days + 1)]


def expired_days(days: Iterable[date], cutoff: datetime) -> list[date]:
    """Return the days whose whole partition lies before the cutoff (its end at or before it)."""
    return sorted(day for day in days if day_start(day + timedelta(days=1)) <= cutoff)


class DayPartitions:
    """One table's day partitions: named, listed, created ahead and dropped whole (metrics', and logs')."""

    def __init__(self, table: str, ahead_days: Callable[[], int]) -> None:
        self.table = table
        self.default_partition = f"{table}_default"
        self.pattern = re.compile(rf"^{table}_p(\d{{8}})$")
        self.ahead_days = ahead_days

    def partition_name(self, day: date) -> str:
        """Return the name of the partition holding a UTC day."""
        return f"{self.table}_p{day:%Y%m%d}"

    def is_partitioned(self, connection: Any = default_connection) -> bool:
        """Tell whether the table is a partitioned table here."""
        if connection.vendor != "postgresql":
            return False
        with connection.cursor() as cursor:
            cursor.execute("SELECT relkind FROM pg_class WHERE oid = to_regclass(%s)", [self.table])
            row = cursor.fetchone()
        return row is not None and row[0] == "p"

    def _locked_and_absent(self, cursor: Any, name: str) -> bool:
        """Take this transaction's lock on the table's partition maintenance; tell whether the partition is missing.

        Beat's hourly tasks, the prunes and several processes may create or drop the same day at
        once; one at a time, each re-reading what exists, none fails on another's work.
        """
        cursor.execute("SELECT pg_advisory_xact_lock(hashtext(%s))", [self.table])
        # pg_class itself, not to_regclass: an advisory lock does not refresh the catalog cache,
        # which may still hold a partition another process dropped.
        cursor.execute(
            "SELECT NOT EXISTS (SELECT FROM pg_class c JOIN pg_namespace n ON n.oid = c.relnamespace"
            " WHERE c.relname = %s AND n.nspname = current_schema())",
            [name],
        )
        return cursor.fetchone()[0]

    def partition_days(self, connection: Any = default_connection) -> list[date]:
        """Return the days that have a partition, oldest first."""
        with connection.cursor() as cursor:
            cursor.execute(
                "SELECT c.relname FROM pg_inherits i JOIN pg_class c ON c.oid = i.inhrelid"
                " WHERE i.inhparent = to_regclass(%s)",
                [self.table],
            )
            names = [row[0] for row in cursor.fetchall()]
        days = []
        for name in names:
            match = self.pattern.match(name)
            if match:
                digits = match.group(1)
                days.append(date(int(digits[:4]), int(digits[4:6]), int(digits[6:])))
        return sorted(days)

    def create_partitions(self, days: Iterable[date], connection: Any = default_connection) -> list[date]:
        """Create the partitions of these days that are missing; return the days created."""
        existing = set(self.partition_days(connection))
        created = []
        table, default = self.table, self.default_partition
        with connection.cursor() as cursor:
            cursor.execute("SELECT to_regclass(%s) IS NOT NULL", [default])
            has_default = cursor.fetchone()[0]
        for day in sorted(set(days) - existing):
            name, start, end = self.partition_name(day), day_start(day), day_start(day + timedelta(days=1))
            with transaction.atomic(using=connection.alias), connection.cursor() as cursor:
                if not self._locked_and_absent(cursor, name):
                    continue  # another process created it meanwhile
                # Rows of this day that went to the default partition would make attaching it fail:
                # build the partition beside the table, move them in, then attach it.
                cursor.execute(f"CREATE TABLE {name} (LIKE {table} INCLUDING DEFAULTS)")
                if has_default:
                    cursor.execute(
                        f"WITH moved AS (DELETE FROM {default} WHERE ts >= %s AND ts < %s RETURNING *)"
                        f" INSERT INTO {name} SELECT * FROM moved",
                        [start, end],
                    )
                # The check lets ATTACH skip scanning the new partition to prove its bounds.
                cursor.execute(
                    f"ALTER TABLE {name} ADD CONSTRAINT {name}_bounds CHECK (ts >= %s AND ts < %s)", [start, end]
                )
                cursor.execute(
                    f"ALTER TABLE {table} ATTACH PARTITION {name} FOR VALUES FROM (%s) TO (%s)", [start, end]
                )
                cursor.execute(f"ALTER TABLE {name} DROP CONSTRAINT {name}_bounds")
            created.append(day)
        return created

    def ensure_partitions(self, now: datetime | None = None, connection: Any = default_connection) -> list[date]:
        """Create the partitions of yesterday, today and the days ahead that are missing; return those created."""
        if not self.is_partitioned(connection):
            return []
        today = day_of(now or timezone.now())
        days = days_between(today - timedelta(days=1), today + timedelta(days=self.ahead_days()))
        return self.create_partitions(days, connection)

    def drop_expired_partitions(self, cutoff: datetime, connection: Any = default_connection) -> int:
        """Drop every day partition wholly before the cutoff; return how many rows went with them."""
        dropped = 0
        for day in expired_days(self.partition_days(connection), cutoff):
            name = self.partition_name(day)
            with transaction.atomic(using=connection.alias), connection.cursor() as cursor:
                if self._locked_and_absent(cursor, name):
                    continue  # another process dropped it meanwhile
                # Counted under the same lock as the drop, so the figure is what was dropped.
                cursor.execute(f"LOCK TABLE {name} IN ACCESS EXCLUSIVE MODE")
                cursor.execute(f"SELECT count(*) FROM {name}")
                dropped += cursor.fetchone()[0]
                cursor.execute(f"DROP TABLE {name}")
        return dropped


METRICS = DayPartitions(TABLE, lambda: settings.BRIDGEOS["METRIC_PARTITION_AHEAD_DAYS"])
DEFAULT_PARTITION = METRICS.default_partition
PARTITION_PATTERN = METRICS.pattern
partition_name = METRICS.partition_name
is_partitioned = METRICS.is_partitioned
partition_days = METRICS.partition_days
create_partitions = METRICS.create_partitions
ensure_partitions = METRICS.ensure_partitions
drop_expired_partitions = METRICS.drop_expired_partitions
