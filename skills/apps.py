"""App config of skills."""

from __future__ import annotations

from django.apps import AppConfig


class SkillsConfig(AppConfig):
    """Register the skills app."""

    name = "skills"
    default_auto_field = "django.db.models.BigAutoField"

    def ready(self) -> None:
        from . import receivers  # noqa: F401 - connects the receivers
