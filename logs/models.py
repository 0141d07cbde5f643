"""Component logs: the lines components print, on robots and in the cloud."""

from __future__ import annotations

from typing import Any

from django.db import models

from .choices import LEVEL_NAME, LOCATIONS, STREAMS


class ComponentLog(models.Model):
    """One line a component printed, named by (robot, skill, component, location, seq, ts).

    On PostgreSQL the table is partitioned by day of ``ts`` (migration 0001, ``logs.partitions``):
    its primary key there is (id, ts). ``robot_id`` is the robot's id rather than a foreign key:
    ingest writes rows straight from frames, and a deleted robot's lines go with it by a receiver
    (one DELETE, not Django's row-by-row cascade over millions of lines).
    """

    robot_id = models.CharField(max_length=64)
    skill = models.CharField(max_length=64)
    component = models.CharField(max_length=64)
    location = models.CharField(max_length=8, choices=[(value, value) for value in LOCATIONS])
    seq = models.BigIntegerField()
    ts = models.DateTimeField()
    stream = models.CharField(max_length=6, choices=[(value, value) for value in STREAMS])
    # The level's rank (0 debug .. 4 critical); null when the line says none.
    level = models.SmallIntegerField(null=True, blank=True)
    text = models.TextField()

    class Meta:
        ordering = ["-ts", "-id"]
        constraints = [
            models.UniqueConstraint(
                fields=["robot_id", "skill", "component", "location", "seq", "ts"], name="componentlog_line_unique"
            )
        ]
        indexes = [models.Index(fields=["robot_id", "ts"], name="componentlog_robot_ts")]
        # On PostgreSQL a trigram index on text serves `q` (migration 0001, when pg_trgm can be created).

    def __str__(self) -> str:
        return f"{self.robot_id} {self.skill}/{self.component} #{self.seq}: {self.text[:80]}"

    @property
    def level_name(self) -> str | None:
        """Return the level's name, or None when the line said none."""
        return None if self.level is None else LEVEL_NAME.get(self.level)


class DroppedLines(models.Model):
    """Lines of a component its robot counted as not shipped (over its caps, or overwritten in its ring)."""

    robot_id = models.CharField(max_length=64)
    skill = models.CharField(max_length=64)
    component = models.CharField(max_length=64)
    location = models.CharField(max_length=8, choices=[(value, value) for value in LOCATIONS])
    ts = models.DateTimeField()
    count = models.PositiveIntegerField()

    class Meta:
        indexes = [models.Index(fields=["robot_id", "ts"], name="droppedlines_robot_ts")]

    def __str__(self) -> str:
        return f"{self.robot_id} {self.skill}/{self.component}: {self.count} dropped"


class ILike(models.Lookup):
    """Case-insensitive LIKE on the column itself, so PostgreSQL's trigram index on ``text`` serves it."""

    lookup_name = "ilike"

    def as_sql(self, compiler: Any, connection: Any) -> tuple[str, list[Any]]:
        lhs, lhs_params = self.process_lhs(compiler, connection)
        rhs, rhs_params = self.process_rhs(compiler, connection)
        # SQLite's LIKE ignores ASCII case already; PostgreSQL's ILIKE does it for every letter.
        operator = "ILIKE" if connection.vendor == "postgresql" else "LIKE"
        return f"{lhs} {operator} {rhs} ESCAPE '\\'", [*lhs_params, *rhs_params]


ComponentLog._meta.get_field("text").register_lookup(ILike)


class CloudLogCursor(models.Model):
    """Where the collection of one cloud copy's output stopped, and the seq its last stored line got."""

    robot_id = models.CharField(max_length=64)
    skill = models.CharField(max_length=64)
    component = models.CharField(max_length=64)
    seq = models.BigIntegerField(default=0)
    # The backend's own mark: {"inode", "offset"} of the process runtime's file, {"since_ns"} of Docker's stream.
    position = models.JSONField(default=dict, blank=True)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["robot_id", "skill", "component"], name="cloudlogcursor_unique")]

    def __str__(self) -> str:
        return f"{self.robot_id} {self.skill}/{self.component} at #{self.seq}"
