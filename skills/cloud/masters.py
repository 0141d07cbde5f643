"""A ROS master per robot in the cloud, for robots that bring none of their own."""

from __future__ import annotations

import logging
import socket
import time

from django.conf import settings
from django.db import transaction
from django.utils import timezone

from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.runtime.base import RuntimeFailure, Status
from monitoring.choices import Level
from monitoring.services import record_event

from ..models import RobotCloud
from .locks import LockBusy, orchestration_lock
from .orchestration import LaunchFailed, TryAgain, enqueue_on_commit, unreachable, with_runtime
from .runtime import (
    runtime_name,
)

logger = logging.getLogger(__name__)

# --------------------------------------------------------------------------- ROS masters


def dedicated_masters() -> bool:
    """Tell whether robots without a ROS master get one of their own in the cloud."""
    configured = settings.BRIDGEOS["CLOUD_ROS_MASTERS"]
    if configured:
        return configured.strip().lower() in ("1", "true", "yes", "on")
    return runtime_name() in ("swarm", "docker")


def ros_master_for(robot_id: str, reported: str | None) -> str:
    """Return the ROS master a connecting robot's components use (in the caller's transaction).

    Its own when it reported one; else the cloud's shared one (BRIDGEOS_CLOUD_ROS_MASTER);
    else, with dedicated masters, one of its own in the cloud, started once this commits.
    """
    if reported:
        return reported
    shared = settings.BRIDGEOS["CLOUD_ROS_MASTER"]
    if shared or not dedicated_masters():
        return shared or ""
    cloud, _ = RobotCloud.objects.select_for_update().get_or_create(robot_id=robot_id)
    if cloud.ros_master_port is None:
        cloud.ros_master_port = _free_master_port()
        cloud.ros_master_status = CS.PENDING
        cloud.save(update_fields=["ros_master_port", "ros_master_status", "updated_at"])
    enqueue_on_commit("ensure_ros_master", robot_id)
    return master_url(cloud.ros_master_port)


def master_url(port: int) -> str:
    """Return the URL of a dedicated ROS master on the cloud host."""
    return f"http://{settings.BRIDGEOS['CLOUD_HOST']}:{port}"


def _free_master_port() -> int:
    """Pick the lowest port of the configured range no other robot holds and nothing listens on."""
    low, _, high = settings.BRIDGEOS["CLOUD_ROS_MASTER_PORTS"].partition("-")
    taken = set(RobotCloud.objects.exclude(ros_master_port=None).values_list("ros_master_port", flat=True))
    for port in range(int(low), int(high or low) + 1):
        if port in taken:
            continue
        with socket.socket() as probe:
            try:
                probe.bind(("0.0.0.0", port))
            except OSError:
                continue
        return port
    raise LaunchFailed(f"no free port for a ROS master in BRIDGEOS_CLOUD_ROS_MASTER_PORTS={low}-{high}")


def converge_ros_master(robot_id: str) -> str:
    """Run the robot's dedicated ROS master while it uses it; stop it once it uses another."""
    try:
        with orchestration_lock(f"master:{robot_id}"):
            cloud = RobotCloud.objects.select_related("robot").filter(robot_id=robot_id).first()
            if cloud is None or cloud.ros_master_port is None:
                return "none"
            wanted = cloud.robot.ros_master == master_url(cloud.ros_master_port)
            try:
                if not wanted:
                    with_runtime(robot_id, lambda runtime: runtime.stop_ros_master())
                    _set_master(cloud, CS.STOPPED)
                    return "stopped"
                state = with_runtime(robot_id, lambda runtime: runtime.start_ros_master(cloud.ros_master_port))
            except RuntimeFailure as exc:
                if unreachable(exc):
                    raise TryAgain(str(exc)) from None
                _set_master(cloud, CS.FAILED, str(exc))
                return "failed"
            if state.status is Status.RUNNING and _answers(cloud.ros_master_port, timeout=15.0):
                _set_master(cloud, CS.RUNNING)
                return "running"
            if state.status is Status.RUNNING:
                raise TryAgain(f"the ROS master of {robot_id} runs but does not answer on {cloud.ros_master_port} yet")
            _set_master(cloud, CS.FAILED, state.message or f"exit code {state.exit_code}")
            return "failed"
    except LockBusy as exc:
        raise TryAgain(str(exc)) from None


def _answers(port: int, *, timeout: float) -> bool:
    """Tell whether something accepts connections on the cloud host's port within ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection((settings.BRIDGEOS["CLOUD_HOST"], port), timeout=1).close()
            return True
        except OSError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.05)


def _set_master(cloud: RobotCloud, status: str, message: str = "") -> None:
    if cloud.ros_master_status == status and cloud.message == message:
        return
    with transaction.atomic():
        RobotCloud.objects.filter(pk=cloud.pk).update(
            ros_master_status=status, message=message, updated_at=timezone.now()
        )
        cloud.ros_master_status, cloud.message = status, message
        text = f"ROS master of robot {cloud.robot_id} on port {cloud.ros_master_port} is {status}"
        record_event(
            text + (f": {message}" if message else ""),
            robot_id=cloud.robot_id,
            level=Level.ERROR if status == CS.FAILED else Level.INFO,
            kind="cloud_ros_master",
            data={"port": cloud.ros_master_port, "status": status},
        )


# --------------------------------------------------------------------------- the reconciler
