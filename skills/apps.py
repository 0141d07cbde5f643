"""App config of skills."""

from __future__ import annotations

from django.apps import AppConfig


class SkillsConfig(AppConfig):
    """Register the skills app."""

    name = "skills"
    default_auto_field = "django.db.models.BigAutoField"

    def ready(self) -> None:
        # Connect the receivers, and register the Celery tasks the orchestration queues by name.
        from . import receivers, tasks  # noqa: F401
