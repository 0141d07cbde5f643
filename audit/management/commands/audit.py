"""`manage.py audit verify`: walk the hash chain; `manage.py audit prune`: apply retention now."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

from django.core.management.base import BaseCommand, CommandError, CommandParser

from audit import services


class Command(BaseCommand):
    help = "Verify the audit trail's hash chain (verify) or delete entries past the retention age (prune)."

    def add_arguments(self, parser: CommandParser) -> None:
        sub = parser.add_subparsers(dest="what", required=True)
        verify = sub.add_parser("verify", help="Recompute every hash; report the first broken link.")
        verify.add_argument("--batch", type=int, default=5000, help="Rows read per round trip (default 5000).")
        prune = sub.add_parser("prune", help="Delete entries older than DAYS (default BRIDGEOS_AUDIT_RETENTION_DAYS).")
        prune.add_argument("--days", type=float, default=None)

    def handle(self, *args: Any, **options: Any) -> None:
        if options["what"] == "prune":
            days = options["days"]
            removed = services.prune_entries(None if days is None else timedelta(days=days))
            self.stdout.write(f"{removed} audit entries removed")
            return
        if options["batch"] < 1:
            raise CommandError("--batch must be at least 1")
        result = services.verify_chain(batch=options["batch"])
        if result.broken is None:
            self.stdout.write(f"audit chain intact: {result.rows} entries verified")
            return
        self.stdout.write(f"{result.rows} entries verified before the break")
        raise CommandError(f"audit chain broken at entry {result.broken.id}: {result.broken.reason}")
