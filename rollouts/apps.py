"""App config of rollouts: immutable, numbered Skill releases and the rollouts that carry them to robots."""

from __future__ import annotations

from django.apps import AppConfig


class RolloutsConfig(AppConfig):
    """Register the rollouts app."""

    name = "rollouts"
    default_auto_field = "django.db.models.BigAutoField"

    def ready(self) -> None:
        # Register the robot door's handler, the Celery tasks beat names, and the families /metrics reads.
        from monitoring import prometheus

        from . import consumers, tasks  # noqa: F401
        from .rolling import write_rollout_families

        prometheus.add_database_families(write_rollout_families)
