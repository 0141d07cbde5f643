"""Choices of monitoring fields."""

from __future__ import annotations

from django.db import models


class Level(models.TextChoices):
    """Severity of an Event."""

    DEBUG = "debug", "Debug"
    INFO = "info", "Info"
    WARNING = "warning", "Warning"
    ERROR = "error", "Error"


class Source(models.TextChoices):
    """Which part of the middleware reported an Event."""

    CLOUD = "cloud", "Cloud"
    ROBOT = "robot", "Robot controller"
    MANAGER = "manager", "Skill manager"
    ROUTER = "router", "Skill router"
    COMPONENT = "component", "Component"
    CLIENT = "client", "Client"
