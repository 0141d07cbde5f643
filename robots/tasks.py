"""Celery tasks of robots: housekeeping of connections."""

from __future__ import annotations

from celery import shared_task

from . import presence


@shared_task(acks_late=True, ignore_result=True)
def sweep_dead_processes() -> list[str]:
    """Mark offline the robots held by server processes that died; return their ids."""
    return presence.sweep_dead_processes()
