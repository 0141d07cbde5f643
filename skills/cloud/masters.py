"""A ROS master per robot in the cloud, for robots that bring none of their own."""

from __future__ import annotations

import logging

from django.conf import settings

from bridgeos_agent.protocol import ComponentStatusName as CS

from ..models import RobotCloud
from .orchestration import enqueue_on_commit
from .perrobot import Service, converge, free_port_in, report, tcp_answers, tcp_bound
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
    taken = set(RobotCloud.objects.exclude(ros_master_port=None).values_list("ros_master_port", flat=True))
    return free_port_in("CLOUD_ROS_MASTER_PORTS", taken, tcp_bound, "a ROS master")


def converge_ros_master(robot_id: str) -> str:
    """Run the robot's dedicated ROS master while it uses it; stop it once it uses another."""

    def find() -> Service | str:
        cloud = RobotCloud.objects.select_related("robot").filter(robot_id=robot_id).first()
        if cloud is None or cloud.ros_master_port is None:
            return "none"
        port = cloud.ros_master_port
        return Service(
            name=f"the ROS master of {robot_id} on port {port}",
            wanted=cloud.robot.ros_master == master_url(port),
            start=lambda runtime: runtime.start_ros_master(port),
            stop=lambda runtime: runtime.stop_ros_master(),
            ready=lambda timeout: tcp_answers(port, timeout),
            report=lambda status, message: _set_master(cloud, status, message),
        )

    return converge(robot_id, f"master:{robot_id}", find)


def _set_master(cloud: RobotCloud, status: str, message: str = "") -> None:
    report(
        cloud,
        "ros_master_status",
        status,
        message,
        robot_id=cloud.robot_id,
        text=f"ROS master of robot {cloud.robot_id} on port {cloud.ros_master_port}",
        kind="cloud_ros_master",
        data={"port": cloud.ros_master_port, "status": status},
    )


# --------------------------------------------------------------------------- the reconciler
