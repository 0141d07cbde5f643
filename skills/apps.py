"""App config of skills."""

from __future__ import annotations

from django.apps import AppConfig


class SkillsConfig(AppConfig):
    """Register the skills app."""

    name = "skills"
    default_auto_field = "django.db.models.BigAutoField"
