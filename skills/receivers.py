"""Answer what the robots app asks by signal: the ROS master and ROS 2 discovery server a connecting robot uses."""

from __future__ import annotations

from typing import Any

from django.dispatch import receiver

from robots.signals import ros2_discovery_wanted, ros_master_wanted

from .cloud.discovery import discovery_server_for
from .cloud.masters import ros_master_for


@receiver(ros_master_wanted, dispatch_uid="skills-ros-master")
def provide_ros_master(sender: Any, robot_id: str, reported: str | None, **kw: Any) -> str:
    """Return the ROS master a connecting robot's components use (its own, the shared one, or one in the cloud)."""
    return ros_master_for(robot_id, reported)


@receiver(ros2_discovery_wanted, dispatch_uid="skills-ros2-discovery")
def provide_ros2_discovery(
    sender: Any, robot_id: str, graph: dict[str, Any] | None, previous: dict[str, Any] | None = None, **kw: Any
) -> str | None:
    """Return "host:port" of the discovery server the cloud runs for a connecting ROS 2 robot (None: no ROS 2)."""
    return discovery_server_for(robot_id, graph, previous)
