"""A Fast DDS discovery server per ROS 2 robot in the cloud: its robot's cloud graph, apart from every other's.

Modelled on the per-robot ROS master (masters.py): a robot that logs in with its ROS 2 graph
gets a UDP port of the cloud host kept for it (``RobotCloud.ros2_discovery_port``), and a
worker task runs ``fast-discovery-server`` there. The robot's cloud copies and the cloud side
of its Skill Router are clients of that server and of nothing else, so robots sharing a host
and a ROS_DOMAIN_ID never discover each other's nodes. Limit: one small server process (about
20 MB resident, measured) and one UDP port of ``BRIDGEOS_CLOUD_ROS2_DISCOVERY_PORTS`` per ROS 2 robot.
"""

from __future__ import annotations

import logging
import socket
from typing import Any

from django.conf import settings

from bridgeos_agent.protocol import ComponentStatusName as CS
from robots.models import Robot

from ..models import RobotCloud
from .orchestration import LaunchFailed, enqueue_on_commit
from .perrobot import Service, converge, free_port_in, report, udp_bound, udp_held
from .runtime import discovery_address

logger = logging.getLogger(__name__)


def discovery_server_for(
    robot_id: str, graph: dict[str, Any] | None, previous: dict[str, Any] | None = None
) -> str | None:
    """Return the discovery server a connecting ROS 2 robot's cloud graph uses (in the caller's transaction).

    None for a robot without ROS 2 (a server it had is stopped once this commits); else
    "host:port" of its own, a port kept for it and the server started once this commits.
    """
    if graph is None and previous is None:
        # Neither now nor at its last login a ROS 2 robot: no query (a connect storm of ROS 1 robots).
        return None
    cloud = RobotCloud.objects.select_for_update().filter(robot_id=robot_id).first()
    if graph is None:
        if cloud is not None and cloud.ros2_discovery_port is not None:
            enqueue_on_commit("ensure_ros2_discovery", robot_id)
        return None
    if cloud is None:
        cloud, _ = RobotCloud.objects.select_for_update().get_or_create(robot_id=robot_id)
    if cloud.ros2_discovery_port is None:
        cloud.ros2_discovery_port = _free_port()
        cloud.ros2_discovery_status = CS.PENDING
        cloud.save(update_fields=["ros2_discovery_port", "ros2_discovery_status", "updated_at"])
    enqueue_on_commit("ensure_ros2_discovery", robot_id)
    return discovery_address(cloud.ros2_discovery_port)


def listen_address() -> str:
    """Return the IP address the servers listen on: the cloud host's (Fast DDS wants an address, not a name)."""
    host = settings.BRIDGEOS["CLOUD_HOST"]
    try:
        return socket.gethostbyname(host)
    except OSError:
        raise LaunchFailed(f"BRIDGEOS_CLOUD_HOST={host!r} does not resolve to an address") from None


def wanted(robot: Robot) -> bool:
    """Tell whether the robot uses its discovery server: it reported a ROS 2 graph at its last login."""
    return robot.ros2 is not None


def _free_port() -> int:
    """Pick the lowest port of the configured range no other robot holds and nothing uses (UDP)."""
    taken = set(RobotCloud.objects.exclude(ros2_discovery_port=None).values_list("ros2_discovery_port", flat=True))
    return free_port_in("CLOUD_ROS2_DISCOVERY_PORTS", taken, udp_bound, "a ROS 2 discovery server")


def converge_discovery_server(robot_id: str) -> str:
    """Run the robot's discovery server while it reports ROS 2; stop it once it no longer does."""

    def find() -> Service | str:
        cloud = RobotCloud.objects.select_related("robot").filter(robot_id=robot_id).first()
        if cloud is None or cloud.ros2_discovery_port is None:
            return "none"
        port = cloud.ros2_discovery_port
        return Service(
            name=f"the ROS 2 discovery server of {robot_id} on UDP port {port}",
            wanted=wanted(cloud.robot),
            start=lambda runtime: runtime.start_discovery_server(listen_address(), port),
            stop=lambda runtime: runtime.stop_discovery_server(),
            ready=lambda timeout: udp_held(port, timeout),
            report=lambda status, message: _set_status(cloud, status, message),
        )

    return converge(robot_id, f"ros2-discovery:{robot_id}", find)


def _set_status(cloud: RobotCloud, status: str, message: str = "") -> None:
    report(
        cloud,
        "ros2_discovery_status",
        status,
        message,
        robot_id=cloud.robot_id,
        text=f"ROS 2 discovery server of robot {cloud.robot_id} on UDP port {cloud.ros2_discovery_port}",
        kind="cloud_ros2_discovery",
        data={"port": cloud.ros2_discovery_port, "status": status},
    )
