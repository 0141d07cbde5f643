"""App config of robots."""

from __future__ import annotations

from django.apps import AppConfig


class RobotsConfig(AppConfig):
    """Register the robots app."""

    name = "robots"
    default_auto_field = "django.db.models.BigAutoField"
