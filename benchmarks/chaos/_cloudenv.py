"""The cloud a hostile or load scenario plays against: its database, Redis, a daphne, and state snapshots."""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

from benchmarks._common import Daphne, ensure_postgres_database, migrate, setup_django

# Used when the runner plays the scenario on its own (the test suite hands it the test database instead).
DEFAULT_DATABASE_URL = "postgres://postgres@127.0.0.1:5432/bridgeos_chaos"
DEFAULT_REDIS_URL = "redis://127.0.0.1:6379/13"
# Robot columns a connection or a disconnection rewrites: they are presence, not state a frame may change.
PRESENCE_COLUMNS = {"connected", "last_seen", "channel", "ros_master", "status"}
PRESENCE_EVENTS = ("connection_established", "connection_lost")


def cloud_env() -> dict[str, str]:
    """Return the environment of the cloud under test, setting Django up in this process if it is not yet."""
    from django.apps import apps

    if apps.ready:
        # Inside the test suite (or after another scenario): serve the database this process already uses.
        from django.conf import settings

        db = settings.DATABASES["default"]
        url = f"postgres://{db['USER']}@{db['HOST'] or '127.0.0.1'}:{db['PORT'] or 5432}/{db['NAME']}"
        env = {"DATABASE_URL": url}
        for key in ("REDIS_URL", "BRIDGEOS_DATA_DIR"):
            if os.environ.get(key):
                env[key] = os.environ[key]
        env.setdefault("BRIDGEOS_DATA_DIR", tempfile.mkdtemp(prefix="bridgeos-chaos-"))
        return env
    env = {
        "DATABASE_URL": os.environ.get("CHAOS_DATABASE_URL", DEFAULT_DATABASE_URL),
        "REDIS_URL": os.environ.get("CHAOS_REDIS_URL", DEFAULT_REDIS_URL),
        "BRIDGEOS_DATA_DIR": tempfile.mkdtemp(prefix="bridgeos-chaos-"),
    }
    ensure_postgres_database(env["DATABASE_URL"])
    migrate(env)
    setup_django(env)
    return env


def start_daphne(env: dict[str, str], name: str, extra: dict[str, str] | None = None) -> Daphne:
    """Start a daphne of the scenario's own and wait until it listens."""
    log_path = Path(env["BRIDGEOS_DATA_DIR"]) / f"{name}-daphne.log"
    daphne = Daphne({**env, **(extra or {})}, log_path)
    daphne.wait()
    return daphne


def snapshot() -> dict[str, str]:
    """Return a digest of every table of the cloud's apps, leaving out robots' presence.

    Presence (connected, last seen, connect/disconnect events) changes whenever a socket opens or
    closes; everything else is state a refused or malformed request must not touch.
    """
    from django.apps import apps
    from django.db.models import Count, Max, Min

    digests = {}
    for label in ("auth", "robots", "skills", "monitoring", "network"):
        for model in apps.get_app_config(label).get_models():
            columns = [f.attname for f in model._meta.concrete_fields]
            rows = model.objects.all()
            if model._meta.label == "robots.Robot":
                columns = [c for c in columns if c not in PRESENCE_COLUMNS]
            if model._meta.label == "monitoring.Event":
                rows = rows.exclude(kind__in=PRESENCE_EVENTS)
            if model._meta.label == "auth.User":
                columns = [c for c in columns if c != "last_login"]
            if model._meta.label == "monitoring.Metric":
                # Too many rows to read whole each time: any insert or delete moves these. (A float sum
                # would not do: PostgreSQL's parallel workers add in varying orders.)
                values = [list(rows.aggregate(Count("pk"), Min("pk"), Max("pk")).values())]
            else:
                values = list(rows.order_by("pk").values_list(*columns))
            text = json.dumps(values, default=str, sort_keys=True)
            digests[model._meta.label] = f"{len(values)} rows {hashlib.sha256(text.encode()).hexdigest()[:16]}"
    return digests


def changed(before: dict[str, str], after: dict[str, str]) -> list[str]:
    """Name the tables whose digest differs."""
    return [
        f"{table}: {before.get(table)} -> {after.get(table)}" for table in after if before.get(table) != after[table]
    ]
