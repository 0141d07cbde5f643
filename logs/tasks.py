"""Celery tasks of logs: retention, partitions and the cloud copies' output."""

from __future__ import annotations

from datetime import timedelta

from celery import shared_task

from . import partitions, services


@shared_task(acks_late=True, autoretry_for=(OSError,), retry_backoff=True, max_retries=5)
def prune_logs(older_than_seconds: float | None = None) -> int:
    """Drop log lines past the retention age (and create the coming days' partitions); return the lines gone."""
    older_than = None if older_than_seconds is None else timedelta(seconds=older_than_seconds)
    return services.prune_logs(older_than)


@shared_task(acks_late=True, autoretry_for=(OSError,), retry_backoff=True, max_retries=5)
def ensure_log_partitions() -> int:
    """Create the log partitions of the coming days that are missing; return how many were created."""
    return len(partitions.ensure_partitions())


@shared_task(ignore_result=True)
def collect_cloud_logs() -> int:
    """Store what the cloud copies printed since the last collection; return the lines stored."""
    from .collector import collect_all

    return collect_all()
