"""App config of teams: organizations, their members' roles, and what each role may do."""

from __future__ import annotations

from django.apps import AppConfig


class TeamsConfig(AppConfig):
    """Register the teams app and give every new user a personal organization."""

    name = "teams"
    verbose_name = "Teams"

    def ready(self) -> None:
        from . import receivers  # noqa: F401  (connects the signal receivers)
