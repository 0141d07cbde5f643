"""Choices of monitoring fields."""

from __future__ import annotations

from typing import TYPE_CHECKING

from django.db import models


class Level(models.TextChoices):
    """Severity of an Event (labels: the names, title-cased)."""

    DEBUG = "debug"
    INFO = "info"
    WARNING = "warning"
    ERROR = "error"


if TYPE_CHECKING:
    from enum import StrEnum

    # mypy runs without Django's plugin and would read each member below as its (value, label)
    # tuple; to it, a source is the string it stores.
    class Source(StrEnum):
        CLOUD = "cloud"
        ROBOT = "robot"
        MANAGER = "manager"
        ROUTER = "router"
        COMPONENT = "component"
        CLIENT = "client"

else:

    class Source(models.TextChoices):
        """Which part of the middleware reported an Event."""

        CLOUD = "cloud", "Cloud"
        ROBOT = "robot", "Robot controller"
        MANAGER = "manager", "Skill manager"
        ROUTER = "router", "Skill router"
        COMPONENT = "component", "Component"
        CLIENT = "client", "Client"
