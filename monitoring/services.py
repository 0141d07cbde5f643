"""Recording and pruning of monitoring data."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
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


def latest_metrics(
    robot_id: str,
    *,
    names: list[str] | None = None,
    skill: str | None = None,
    component: str | None = None,
    since: float | None = None,
    limit: int = 100,
) -> list[dict[str, Any]]:
    """Return metric points of a robot: the latest of each series, or all since a time."""
    points = Metric.objects.filter(robot_id=robot_id)
    if names:
        points = points.filter(name__in=names)
    if skill is not None:
        points = points.filter(skill=skill)
    if component is not None:
        points = points.filter(component=component)
    if since is not None:
        points = points.filter(ts__gte=datetime.fromtimestamp(since, tz=UTC)).order_by("-ts")
    elif connection.vendor == "postgresql":
        points = points.order_by("name", "skill", "component", "-ts").distinct("name", "skill", "component")
    else:
        latest: dict[tuple[str, str, str], Metric] = {}
        for point in points.order_by("-ts")[: limit * 50]:
            latest.setdefault((point.name, point.skill, point.component), point)
        points = list(latest.values())
    return [_point(metric) for metric in points[:limit]]


def _point(metric: Metric) -> dict[str, Any]:
    point: dict[str, Any] = {"name": metric.name, "value": metric.value, "ts": metric.ts.timestamp()}
    if metric.skill:
        point["skill"] = metric.skill
    if metric.component:
        point["component"] = metric.component
    if metric.labels:
        point["labels"] = metric.labels
    return point
