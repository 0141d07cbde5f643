"""Celery tasks of the audit trail: retention."""

from __future__ import annotations

from celery import shared_task

from . import services


@shared_task(acks_late=True, autoretry_for=(OSError,), retry_backoff=True, max_retries=5)
def prune_audit() -> int:
    """Delete audit entries past BRIDGEOS_AUDIT_RETENTION_DAYS; return how many went."""
    return services.prune_entries()
