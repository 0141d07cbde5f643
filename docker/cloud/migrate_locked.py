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


def adopt_ca() -> None:
    """Make the stack's CA (BRIDGEOS_STACK_CA_CERT_FILE and _KEY_FILE) the cloud's, if it has none yet.

    scripts/deploy.sh issued the registry's TLS certificate from it before any database existed; robots
    pinning the cloud's CA then trust the registry too. Under the migration lock, so one container adopts it.
    """
    cert_file = os.environ.get("BRIDGEOS_STACK_CA_CERT_FILE")
    key_file = os.environ.get("BRIDGEOS_STACK_CA_KEY_FILE")
    if not cert_file or not key_file:
        return
    from network.models import Authority

    with open(cert_file) as cert, open(key_file) as key:
        cert_pem, key_pem = cert.read(), key.read()
    existing = Authority.objects.filter(name="ca").first()
    if existing is None:
        Authority.objects.create(name="ca", cert_pem=cert_pem, key_pem=key_pem)
        print("migrate: the stack's CA is now the cloud's CA", flush=True)
    elif existing.cert_pem.strip() != cert_pem.strip():
        # A database older than the stack's CA keeps its own: replacing it would orphan robots' certificates.
        print(
            f"migrate: WARNING: the database holds another cloud CA than {cert_file}; robots pinning it will"
            " not trust the stack's registry (give them the stack's ca.crt with --ca)",
            file=sys.stderr,
            flush=True,
        )


def main() -> None:
    """Migrate under the lock, then create the operator account if it is missing."""
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "bridgeos_cloud.settings")
    django.setup()
    from django.core.management import call_command
    from django.db import connection

    wait_for_database()
    if connection.vendor != "postgresql":
        call_command("migrate", interactive=False, verbosity=1)
        adopt_ca()
    else:
        with connection.cursor() as cursor:
            cursor.execute("SELECT pg_advisory_lock(%s)", [MIGRATION_LOCK])
            try:
                call_command("migrate", interactive=False, verbosity=1)
                adopt_ca()
            finally:
                cursor.execute("SELECT pg_advisory_unlock(%s)", [MIGRATION_LOCK])
    if os.environ.get("DJANGO_SUPERUSER_PASSWORD"):
        call_command("ensure_operator")


if __name__ == "__main__":
    main()
