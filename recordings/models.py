"""MCAP recordings of a robot's topics, kept by the cloud."""

from __future__ import annotations

import uuid
from pathlib import Path

from django.conf import settings
from django.db import models
from django.utils import timezone

from robots.models import Robot

from .choices import RUNNING, RecordingStatus, RosProfile


class Recording(models.Model):
    """One recording: what was asked, what the robot reported, and the .mcap file once assembled."""

    id = models.UUIDField(primary_key=True, default=uuid.uuid4, editable=False)
    robot = models.ForeignKey(Robot, on_delete=models.CASCADE, related_name="recordings")
    topics = models.JSONField(help_text='The topics recorded, e.g. ["/chatter"].')
    ros = models.CharField(max_length=8, choices=RosProfile.choices, blank=True)
    status = models.CharField(max_length=16, choices=RecordingStatus.choices, default=RecordingStatus.STARTING)
    # Why it ended: "stopped", "size limit reached", "duration limit reached", or what failed.
    message = models.CharField(max_length=2000, blank=True)
    max_bytes = models.BigIntegerField()
    max_duration_s = models.FloatField()
    created_at = models.DateTimeField(default=timezone.now, editable=False)
    started_at = models.DateTimeField(null=True, blank=True)
    stopped_at = models.DateTimeField(null=True, blank=True)
    duration_s = models.FloatField(null=True, blank=True)
    message_count = models.BigIntegerField(default=0)
    data_bytes = models.BigIntegerField(default=0, help_text="Bytes of the messages recorded.")
    size_bytes = models.BigIntegerField(default=0, help_text="Bytes of the .mcap file.")
    # How many chunks the robot sent (known when it ended), and the robot's own final word (finished/failed).
    chunks = models.IntegerField(null=True, blank=True)
    outcome = models.CharField(max_length=16, choices=RecordingStatus.choices, blank=True)
    # The .mcap file, relative to the recordings directory, once every chunk arrived.
    file = models.CharField(max_length=500, blank=True)

    class Meta:
        ordering = ["-created_at"]
        indexes = [models.Index(fields=["robot", "-created_at"])]

    def __str__(self) -> str:
        return f"recording {self.id.hex} of {self.robot_id}"

    @property
    def running(self) -> bool:
        return self.status in RUNNING

    @property
    def folder(self) -> Path:
        """Return where this recording's chunks and file are kept."""
        return Path(settings.BRIDGEOS["RECORDINGS_DIR"]) / self.robot_id / self.id.hex

    @property
    def path(self) -> Path | None:
        """Return the assembled .mcap file, if there is one."""
        return Path(settings.BRIDGEOS["RECORDINGS_DIR"]) / self.file if self.file else None
