"""App config of monitoring."""

from __future__ import annotations

from django.apps import AppConfig


class MonitoringConfig(AppConfig):
    """Register the monitoring app."""

    name = "monitoring"
    default_auto_field = "django.db.models.BigAutoField"

    def ready(self) -> None:
        from . import receivers  # noqa: F401 - connects the receivers
        from .prometheus import watch_celery_tasks

        # Celery's signals are process-wide: in a worker they fire, elsewhere they never do.
        watch_celery_tasks()
