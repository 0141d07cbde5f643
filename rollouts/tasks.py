"""Celery task of rollouts: the executor's tick, run by beat every BRIDGEOS_ROLLOUT_TICK_S."""

from __future__ import annotations

from celery import shared_task

from . import executor


@shared_task(ignore_result=True)
def advance_rollouts() -> int:
    """Move every active rollout one step."""
    return executor.tick()
