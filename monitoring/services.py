"""Recording and pruning of monitoring data."""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from django.conf import settings
from django.db import connection, transaction
from django.utils import timezone

from .choices import Level, Source
from .models import Event, Metric


def record_event(
    message: str,
    *,
    robot_id: str | None = None,
    level: str = Level.INFO,
    source: str = Source.CLOUD,
    kind: str = "",
    skill: str = "",
    component: str = "",
    data: dict[str, Any] | None = None,
) -> Event:
    """Append one entry to the event log."""
    return Event.objects.create(
        robot_id=robot_id,
        level=level,
        source=source,
        kind=kind,
        skill=skill,
        component=component,
        message=message,
        data=data or {},
    )


def prune_metrics(older_than: timedelta | None = None, *, now: datetime | None = None, batch: int = 50_000) -> int:
    """Delete metric points older than the retention age and return how many went."""
    if older_than is None:
        older_than = timedelta(days=settings.BRIDGEOS["METRIC_RETENTION_DAYS"])
    cutoff = (now or timezone.now()) - older_than
    deleted = 0
    # Deleting in bounded batches keeps each transaction and its locks short on a big table.
    while True:
        with transaction.atomic():
            ids = list(Metric.objects.filter(ts__lt=cutoff).values_list("id", flat=True)[:batch])
            if not ids:
                return deleted
            if connection.vendor == "postgresql":
                with connection.cursor() as cursor:
                    cursor.execute("DELETE FROM monitoring_metric WHERE id = ANY(%s)", [ids])
            else:
                Metric.objects.filter(id__in=ids).delete()
        deleted += len(ids)
