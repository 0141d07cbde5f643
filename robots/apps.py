"""App config of robots."""

from __future__ import annotations

from django.apps import AppConfig

from monitoring import prometheus


class RobotsConfig(AppConfig):
    """Register the robots app."""

    name = "robots"
    default_auto_field = "django.db.models.BigAutoField"

    def ready(self) -> None:
        from . import receivers  # noqa: F401 - connects the receivers
        from .services import write_robot_families

        prometheus.add_database_families(write_robot_families)
