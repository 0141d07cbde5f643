"""App config of recordings."""

from __future__ import annotations

from django.apps import AppConfig


class RecordingsConfig(AppConfig):
    """Register the recordings app."""

    name = "recordings"
    default_auto_field = "django.db.models.BigAutoField"

    def ready(self) -> None:
        from django.db.models.signals import post_delete

        # consumers: the robot door's handlers of recording chunks and statuses.
        from . import consumers, models, services  # noqa: F401

        # A deleted recording's files go with it, however it is deleted (its robot's or owner's deletion too).
        post_delete.connect(services.remove_files, sender=models.Recording, dispatch_uid="recordings.remove_files")
