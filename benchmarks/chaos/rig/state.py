"""What a cloud served from this process holds: a digest of every table, to prove a request changed nothing."""

from __future__ import annotations

import hashlib
import json

# Robot columns a connection or a disconnection rewrites: they are presence, not state a frame may change.
PRESENCE_COLUMNS = {"connected", "last_seen", "channel", "ros_master", "status"}
PRESENCE_EVENTS = ("connection_established", "connection_lost")


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
