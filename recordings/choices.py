"""Choices of recording fields."""

from __future__ import annotations

from django.db import models

from bridgeos_agent.protocol import RecordingStatusName


class RecordingStatus(models.TextChoices):
    """Where a recording is: the robot's states (protocol.RecordingStatusName), kept by the cloud."""

    STARTING = RecordingStatusName.STARTING.value, "Starting"
    RECORDING = RecordingStatusName.RECORDING.value, "Recording"
    STOPPING = RecordingStatusName.STOPPING.value, "Stopping"
    FINISHED = RecordingStatusName.FINISHED.value, "Finished"
    FAILED = RecordingStatusName.FAILED.value, "Failed"


# A robot runs one recording at a time: these are the states of the one it runs.
RUNNING = (RecordingStatus.STARTING, RecordingStatus.RECORDING)


class RosProfile(models.TextChoices):
    """The ROS a recording's topics come from, as MCAP names its profile."""

    ROS1 = "ros1", "ROS 1"
    ROS2 = "ros2", "ROS 2"
