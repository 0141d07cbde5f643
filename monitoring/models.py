"""Monitoring data: metric points and the event log."""

from __future__ import annotations

from django.db import models
from django.utils import timezone

from .choices import Level, Source


class Metric(models.Model):
    """One measured point of a robot, or of one of its skills or components."""

    # No index of its own: the (robot, name, ts) index serves lookups by robot, and each index slows ingest.
    # No constraint in the database either: its row-by-row check was 40 % of a point's cost to store.
    # Ingest locks a batch's robots instead, and their deletion their rows (monitoring.sinks says how).
    robot = models.ForeignKey(
        "robots.Robot", on_delete=models.CASCADE, related_name="metrics", db_index=False, db_constraint=False
    )
    # Slugs rather than foreign keys: ingest writes them straight from frames, with no lookups.
    skill = models.CharField(max_length=64, blank=True, default="")
    component = models.CharField(max_length=64, blank=True, default="")
    name = models.CharField(max_length=128)
    value = models.FloatField()
    labels = models.JSONField(default=dict, blank=True)
    ts = models.DateTimeField()

    class Meta:
        ordering = ["-ts"]
        indexes = [models.Index(fields=["robot", "name", "ts"], name="metric_robot_name_ts")]
        # A BRIN index on ts is added on PostgreSQL by migration 0002.

    def __str__(self) -> str:
        return f"{self.robot_id} {self.name}={self.value} @ {self.ts:%Y-%m-%d %H:%M:%S}"


class Event(models.Model):
    """One entry of the log: what happened to a robot, skill or component."""

    ts = models.DateTimeField(default=timezone.now)
    level = models.CharField(max_length=8, choices=Level.choices, default=Level.INFO)
    source = models.CharField(max_length=16, choices=Source.choices, default=Source.CLOUD)
    kind = models.CharField(max_length=64, blank=True, help_text="The protocol event it records, if any.")
    robot = models.ForeignKey("robots.Robot", on_delete=models.CASCADE, related_name="events", null=True, blank=True)
    skill = models.CharField(max_length=64, blank=True, default="")
    component = models.CharField(max_length=64, blank=True, default="")
    message = models.TextField()
    data = models.JSONField(default=dict, blank=True)

    class Meta:
        ordering = ["-ts"]
        indexes = [
            models.Index(fields=["robot", "ts"], name="event_robot_ts"),
            models.Index(fields=["ts"], name="event_ts"),
        ]

    def __str__(self) -> str:
        return f"[{self.level}] {self.message}"


class IngestedFrame(models.Model):
    """A robot's acked frame whose effects were committed: written in the same transaction as them.

    Metrics frames claim their ids with their rows (ingest), every other report with what its
    handler writes (`robots.dbthreads.sync`). A robot resends a frame whose ack it never got (the
    cloud killed, a store restarted); with its id here the resent copy is recognised and not
    applied twice, whatever happened to the consumers' in-memory and Redis windows meanwhile.
    """

    robot_id = models.CharField(max_length=64)
    frame_id = models.CharField(max_length=64)
    created = models.DateTimeField(default=timezone.now)

    class Meta:
        constraints = [models.UniqueConstraint(fields=["robot_id", "frame_id"], name="ingested_frame_unique")]

    def __str__(self) -> str:
        return f"{self.robot_id} {self.frame_id}"
