"""App config of logs."""

from __future__ import annotations

from django.apps import AppConfig


class LogsConfig(AppConfig):
    """Register the logs app."""

    name = "logs"
    default_auto_field = "django.db.models.BigAutoField"

    def ready(self) -> None:
        # consumers: the robot door's handler of component_logs; receivers: a deleted robot's lines go with it.
        from . import consumers, receivers, tasks  # noqa: F401
