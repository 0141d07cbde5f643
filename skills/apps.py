"""App config of skills."""

from __future__ import annotations

from django.apps import AppConfig

from monitoring import prometheus


class SkillsConfig(AppConfig):
    """Register the skills app."""

    name = "skills"
    default_auto_field = "django.db.models.BigAutoField"

    def ready(self) -> None:
        # Connect the receivers, register the Celery tasks the orchestration queues by name and
        # the robot door's handlers of Skill volumes and cloud copies.
        from . import consumers, receivers, tasks  # noqa: F401
        from .services import write_cloud_copy_families

        prometheus.add_database_families(write_cloud_copy_families)
