"""The log table's time partitions on PostgreSQL: one per UTC day, created ahead, dropped whole when expired.

The same scheme as the metric table's (`monitoring.partitions`, whose `DayPartitions` this
uses): a partition `logs_componentlog_pYYYYMMDD` per day, a default partition for any line no
day covers (a robot clock far off), and retention by dropping whole days. The primary key is
(id, ts) and the line's key (robot, skill, component, location, seq, ts) is unique, both holding
the partition key as PostgreSQL requires. The embedded SQLite default keeps a plain table.
"""

from __future__ import annotations

from monitoring.partitions import DayPartitions, day_of, day_start, days_between

__all__ = [
    "AHEAD_DAYS",
    "DEFAULT_PARTITION",
    "LOGS",
    "PARTITION_PATTERN",
    "TABLE",
    "create_partitions",
    "day_of",
    "day_start",
    "days_between",
    "drop_expired_partitions",
    "ensure_partitions",
    "is_partitioned",
    "partition_days",
    "partition_name",
]

TABLE = "logs_componentlog"
# Logs are kept days, not months: two days ahead is plenty with the hourly task and the default partition.
AHEAD_DAYS = 2

LOGS = DayPartitions(TABLE, lambda: AHEAD_DAYS)
DEFAULT_PARTITION = LOGS.default_partition
PARTITION_PATTERN = LOGS.pattern
partition_name = LOGS.partition_name
is_partitioned = LOGS.is_partitioned
partition_days = LOGS.partition_days
create_partitions = LOGS.create_partitions
ensure_partitions = LOGS.ensure_partitions
drop_expired_partitions = LOGS.drop_expired_partitions
