"""Delete metric points older than the retention age."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser

from monitoring.services import prune_metrics


class Command(BaseCommand):
    help = "Delete metric points older than DAYS (default: BRIDGEOS_METRIC_RETENTION_DAYS) and print how many."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument(
            "--older-than", type=float, metavar="DAYS", help="Age in days, fractions allowed (default: retention)."
        )

    def handle(self, *args: Any, **options: Any) -> None:
        days = options["older_than"]
        if days is not None and days < 0:
            raise CommandError("--older-than must not be negative.")
        deleted = prune_metrics(None if days is None else timedelta(days=days))
        self.stdout.write(f"Deleted {deleted} metric points.")
