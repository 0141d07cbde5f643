"""Celery tasks of monitoring: housekeeping of metrics."""

from __future__ import annotations

from datetime import timedelta

from celery import shared_task

from . import services


@shared_task(acks_late=True, autoretry_for=(OSError,), retry_backoff=True, max_retries=5)
def prune_metrics(older_than_seconds: float | None = None) -> int:
    """Delete metric points past the retention age (and old ingested frame ids); return the points deleted."""
    older_than = None if older_than_seconds is None else timedelta(seconds=older_than_seconds)
    deleted = services.prune_metrics(older_than)
    services.prune_ingested_frames()
    return deleted
