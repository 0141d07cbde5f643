"""Answer what the robots app asks by signal: the ROS master a connecting robot uses."""

from __future__ import annotations

from typing import Any

from django.dispatch import receiver

from robots.signals import ros_master_wanted

from .cloud.masters import ros_master_for


@receiver(ros_master_wanted, dispatch_uid="skills-ros-master")
def provide_ros_master(sender: Any, robot_id: str, reported: str | None, **kw: Any) -> str:
    """Return the ROS master a connecting robot's components use (its own, the shared one, or one in the cloud)."""
    return ros_master_for(robot_id, reported)
