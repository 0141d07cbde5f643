"""Partition monitoring_metric by day of ts on PostgreSQL, keeping every existing row.

The table is renamed aside, a partitioned table of the same columns takes its name, a day
partition is created for each day of the retention window that holds rows (and for the days
ahead), rows are copied over (older ones land in the default partition, which the next prune
empties), and the old table is dropped. The copy rewrites the table once, under an exclusive
lock: ingest waits (robots resend from their outbox) for as long as it takes. The primary key
becomes (id, ts), as PostgreSQL requires; ids keep their values and their sequence goes on.
Django's model state does not change: it still knows `id` as the primary key.
"""

from __future__ import annotations

from datetime import timedelta

from django.conf import settings
from django.db import migrations
from django.utils import timezone

from monitoring import partitions

TABLE = partitions.TABLE
OLD = f"{TABLE}_unpartitioned"
COLUMNS = "id, skill, component, name, value, labels, ts, robot_id"
SEQUENCE = f"{TABLE}_id_seq"


def _foreign_key(cursor, table: str) -> tuple[str, str]:
    """Return the name and definition of the table's foreign key to robots."""
    cursor.execute(
        "SELECT conname, pg_get_constraintdef(oid) FROM pg_constraint"
        " WHERE conrelid = to_regclass(%s) AND contype = 'f'",
        [table],
    )
    return cursor.fetchone()


def _create_indexes(cursor, table: str) -> None:
    cursor.execute(f"CREATE INDEX metric_robot_name_ts ON {table} (robot_id, name, ts)")
    # Rows arrive in time order, so a BRIN index answers time ranges inside a partition at a tiny size.
    cursor.execute(f"CREATE INDEX metric_ts_brin ON {table} USING brin (ts) WITH (pages_per_range = 32)")


def partition(apps, schema_editor):
    connection = schema_editor.connection
    if connection.vendor != "postgresql":
        return  # SQLite (make run's default) keeps a plain table and deletes expired rows
    if partitions.is_partitioned(connection):
        return  # converted already (by an earlier copy of this migration): nothing to do
    with connection.cursor() as cursor:
        cursor.execute(f"LOCK TABLE {TABLE} IN ACCESS EXCLUSIVE MODE")
        fk_name, fk_definition = _foreign_key(cursor, TABLE)
        cursor.execute(f"SELECT max(id), min(ts) FROM {TABLE}")
        max_id, first_ts = cursor.fetchone()
        cursor.execute(f"ALTER TABLE {TABLE} RENAME TO {OLD}")
        cursor.execute(f"ALTER TABLE {OLD} DROP CONSTRAINT {fk_name}")
        cursor.execute("DROP INDEX IF EXISTS metric_robot_name_ts, metric_ts_brin")
        # The identity's sequence carries the table's old name: it goes, a plain sequence takes over.
        cursor.execute(f"ALTER TABLE {OLD} ALTER COLUMN id DROP IDENTITY IF EXISTS")
        cursor.execute(f"ALTER TABLE {OLD} RENAME CONSTRAINT {TABLE}_pkey TO {OLD}_pkey")
        cursor.execute(f"CREATE TABLE {TABLE} (LIKE {OLD} INCLUDING DEFAULTS) PARTITION BY RANGE (ts)")
        cursor.execute(f"CREATE SEQUENCE {SEQUENCE} OWNED BY {TABLE}.id")
        cursor.execute(f"ALTER TABLE {TABLE} ALTER COLUMN id SET DEFAULT nextval('{SEQUENCE}')")
        cursor.execute(f"ALTER TABLE {TABLE} ADD CONSTRAINT {TABLE}_pkey PRIMARY KEY (id, ts)")
        cursor.execute(f"CREATE TABLE {partitions.DEFAULT_PARTITION} PARTITION OF {TABLE} DEFAULT")
    now = timezone.now()
    today = partitions.day_of(now)
    retained = partitions.day_of(now - timedelta(days=settings.BRIDGEOS["METRIC_RETENTION_DAYS"]))
    first = max(retained, partitions.day_of(first_ts)) if first_ts is not None else today
    last = today + timedelta(days=settings.BRIDGEOS["METRIC_PARTITION_AHEAD_DAYS"])
    partitions.create_partitions(partitions.days_between(min(first, today), last), connection)
    with connection.cursor() as cursor:
        cursor.execute(f"INSERT INTO {TABLE} ({COLUMNS}) SELECT {COLUMNS} FROM {OLD}")
        cursor.execute(f"DROP TABLE {OLD}")
        if max_id is not None:
            cursor.execute("SELECT setval(%s, %s)", [SEQUENCE, max_id])
        _create_indexes(cursor, TABLE)
        cursor.execute(f"ALTER TABLE {TABLE} ADD CONSTRAINT {fk_name} {fk_definition}")
        cursor.execute(f"ANALYZE {TABLE}")


def unpartition(apps, schema_editor):
    connection = schema_editor.connection
    if connection.vendor != "postgresql" or not partitions.is_partitioned(connection):
        return
    with connection.cursor() as cursor:
        cursor.execute(f"LOCK TABLE {TABLE} IN ACCESS EXCLUSIVE MODE")
        fk_name, fk_definition = _foreign_key(cursor, TABLE)
        cursor.execute(f"SELECT max(id) FROM {TABLE}")
        max_id = cursor.fetchone()[0]
        cursor.execute(f"ALTER TABLE {TABLE} RENAME TO {OLD}")
        cursor.execute(f"ALTER TABLE {OLD} DROP CONSTRAINT {fk_name}")
        cursor.execute(f"ALTER TABLE {OLD} RENAME CONSTRAINT {TABLE}_pkey TO {OLD}_pkey")
        cursor.execute("DROP INDEX IF EXISTS metric_robot_name_ts, metric_ts_brin")
        cursor.execute(f"CREATE TABLE {TABLE} (LIKE {OLD})")
        cursor.execute(f"INSERT INTO {TABLE} ({COLUMNS}) SELECT {COLUMNS} FROM {OLD}")
        cursor.execute(f"DROP TABLE {OLD}")  # its partitions and sequence go with it
        cursor.execute(f"ALTER TABLE {TABLE} ALTER COLUMN id ADD GENERATED BY DEFAULT AS IDENTITY")
        cursor.execute(f"ALTER TABLE {TABLE} ADD CONSTRAINT {TABLE}_pkey PRIMARY KEY (id)")
        if max_id is not None:
            cursor.execute(f"SELECT setval(pg_get_serial_sequence('{TABLE}', 'id'), %s)", [max_id])
        _create_indexes(cursor, TABLE)
        cursor.execute(f"ALTER TABLE {TABLE} ADD CONSTRAINT {fk_name} {fk_definition}")


class Migration(migrations.Migration):
    # One transaction: a failure half-way leaves the plain table as it was.
    atomic = True
    dependencies = [("monitoring", "0004_ingested_frame")]
    operations = [migrations.RunPython(partition, unpartition)]
