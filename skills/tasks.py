"""Celery tasks of the cloud orchestration: thin doors to `skills.cloud`.

Each takes primary keys (and the launch token of the request it serves), is acknowledged
only once done (``acks_late``; a worker that dies mid-task has it redelivered, and the
repeated step adopts what the first attempt created), retries what may pass, and rolls a
start back when it gives up.
"""

from __future__ import annotations

from celery import Task, shared_task

from .cloud import converge, masters, reconcile
from .cloud.orchestration import TryAgain

RETRIES = 4


def _backoff(retries: int) -> float:
    return min(1.0 * 2**retries, 15.0)


@shared_task(bind=True, acks_late=True, reject_on_worker_lost=True, max_retries=RETRIES)
def start_cloud_component(self: Task, instance_id: int, token: str) -> str:
    """Run a component's cloud copy for the start request with this token."""
    try:
        return converge.converge(instance_id, token)
    except TryAgain as exc:
        if self.request.retries < self.max_retries:
            raise self.retry(exc=exc, countdown=_backoff(self.request.retries)) from None
        converge.give_up(instance_id, token, f"gave up after {self.max_retries + 1} attempts: {exc}")
        return "failed"


@shared_task(bind=True, acks_late=True, reject_on_worker_lost=True, max_retries=RETRIES)
def stop_cloud_component(self: Task, instance_id: int, token: str) -> str:
    """Remove a component's cloud copy for the stop request with this token."""
    try:
        return converge.converge(instance_id, token)
    except TryAgain as exc:
        if self.request.retries < self.max_retries:
            raise self.retry(exc=exc, countdown=_backoff(self.request.retries)) from None
        # The reconciler removes it once the engine answers again: the row already wants it gone.
        return "left to the reconciler"


@shared_task(bind=True, acks_late=True, reject_on_worker_lost=True, max_retries=RETRIES)
def ensure_ros_master(self: Task, robot_id: str) -> str:
    """Run (or stop) a robot's dedicated ROS master as its row says."""
    try:
        return masters.converge_ros_master(robot_id)
    except TryAgain as exc:
        if self.request.retries < self.max_retries:
            raise self.retry(exc=exc, countdown=_backoff(self.request.retries)) from None
        return "left to the reconciler"


@shared_task(acks_late=True, ignore_result=True)
def reconcile_cloud() -> dict[str, int]:
    """Compare the desired cloud copies with what runs and fix the difference."""
    return reconcile.reconcile()
