"""Choices of robot fields."""

from __future__ import annotations

from django.db import models


class RobotStatus(models.TextChoices):
    """Where a Robot Controller is in its life cycle (thesis §3.3)."""

    IDLE = "idle", "Idle"
    RUNNING = "running", "Running"
    STOPPED = "stopped", "Stopped"
    SHUTDOWN = "shutdown", "Shut down"
