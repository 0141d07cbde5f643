"""App config of recordings."""

from __future__ import annotations

from django.apps import AppConfig


class RecordingsConfig(AppConfig):
    """Register the recordings app."""

    name = "recordings"
    default_auto_field = "django.db.models.BigAutoField"

    def ready(self) -> None:
        # The robot door's handlers of recording chunks and statuses.
        from . import consumers  # noqa: F401
