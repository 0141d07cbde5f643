"""Celery tasks of the cloud orchestration: thin doors to `skills.cloud`.

Each takes primary keys (and the launch token of the request it serves), is acknowledged
only once done (``acks_late``; a worker that dies mid-task has it redelivered, and the
repeated step adopts what the first attempt created), retries what may pass (the policy
is declared once, in `RETRIED`, and given to each decorator), and rolls a start back when
it gives up.
"""

from __future__ import annotations

from typing import Any

from celery import Task, shared_task

from .cloud import converge, discovery, masters, reconcile, relay
from .cloud.orchestration import TryAgain

RETRIES = 4

# A step that could not be done now (engine unreachable, lock busy) is retried after 1, 2, 4, 8 s
# (at most 15 s), then given up on; TryAgain is expected, so its last failure is logged without a traceback.
RETRIED: dict[str, Any] = {
    "bind": True,
    "acks_late": True,
    "reject_on_worker_lost": True,
    "autoretry_for": (TryAgain,),
    "throws": (TryAgain,),
    "max_retries": RETRIES,
    "retry_backoff": 1,
    "retry_backoff_max": 15,
    "retry_jitter": False,
}


class StartTask(Task):
    """A start request: once its retries are spent, roll the start back for good."""

    def on_failure(self, exc: BaseException, task_id: str, args: Any, kwargs: Any, einfo: Any) -> None:
        if isinstance(exc, TryAgain):
            instance_id, token = args
            converge.give_up(instance_id, token, f"gave up after {self.max_retries + 1} attempts: {exc}")


@shared_task(base=StartTask, **RETRIED)
def start_cloud_component(self: Task, instance_id: int, token: str) -> str:
    """Run a component's cloud copy for the start request with this token."""
    return converge.converge(instance_id, token)


@shared_task(**RETRIED)
def stop_cloud_component(self: Task, instance_id: int, token: str) -> str:
    """Remove a component's cloud copy for the stop request with this token."""
    # Given up on, the reconciler removes it once the engine answers again: the row already wants it gone.
    return converge.converge(instance_id, token)


@shared_task(**RETRIED)
def ensure_ros_master(self: Task, robot_id: str) -> str:
    """Run (or stop) a robot's dedicated ROS master as its row says."""
    # Given up on, the reconciler starts or stops it on its next round.
    return masters.converge_ros_master(robot_id)


@shared_task(**RETRIED)
def ensure_ros2_discovery(self: Task, robot_id: str) -> str:
    """Run (or stop) a ROS 2 robot's discovery server as its row says."""
    # Given up on, the reconciler starts or stops it on its next round.
    return discovery.converge_discovery_server(robot_id)


@shared_task(acks_late=True, ignore_result=True)
def reconcile_cloud() -> dict[str, int]:
    """Compare the desired cloud copies with what runs and fix the difference."""
    return reconcile.reconcile()


@shared_task(**RETRIED)
def ensure_cloud_relay(self: Task, robot_id: str, skill_id: str) -> str:
    """Run (or stop) a robot Skill's cloud relay as its row says."""
    # Given up on, the reconciler starts or stops it on its next round.
    return relay.converge_relay(robot_id, skill_id)
