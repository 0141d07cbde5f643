"""Apply migrations once however many containers start together, then ensure the operator account.

Every daphne and worker container runs this before it serves: the first takes a PostgreSQL
advisory lock and migrates, the others wait on the lock and then find nothing to do. A rolling
update therefore migrates before the first new replica serves (migrations must stay compatible
with the replicas still running the old code until they are replaced).
"""

from __future__ import annotations

import os
import sys
import time

import django

# Any fixed number names the lock; this one spells "brid".
MIGRATION_LOCK = 0x62726964
DATABASE_WAIT_S = float(os.environ.get("BRIDGEOS_DATABASE_WAIT_S", "120"))


def wait_for_database() -> None:
    """Retry until the database answers: in a fresh stack PostgreSQL starts alongside the cloud."""
    from django.db import connection
    from django.db.utils import OperationalError

    deadline = time.monotonic() + DATABASE_WAIT_S
    while True:
        try:
            connection.ensure_connection()
            return
        except OperationalError as exc:
            if time.monotonic() > deadline:
                sys.exit(f"migrate: the database did not answer within {DATABASE_WAIT_S:.0f} s: {exc}")
            time.sleep(1)


def main() -> None:
    """Migrate under the lock, then create the operator account if it is missing."""
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "bridgeos_cloud.settings")
    django.setup()
    from django.core.management import call_command
    from django.db import connection

    wait_for_database()
    if connection.vendor != "postgresql":
        call_command("migrate", interactive=False, verbosity=1)
    else:
        with connection.cursor() as cursor:
            cursor.execute("SELECT pg_advisory_lock(%s)", [MIGRATION_LOCK])
            try:
                call_command("migrate", interactive=False, verbosity=1)
            finally:
                cursor.execute("SELECT pg_advisory_unlock(%s)", [MIGRATION_LOCK])
    if os.environ.get("DJANGO_SUPERUSER_PASSWORD"):
        call_command("ensure_operator")


if __name__ == "__main__":
    main()
