"""Answer what the robots app asks by signal (a connecting robot's ROS master, discovery server, cloud relays)."""

from __future__ import annotations

from typing import Any

from django.db.models.signals import post_delete
from django.dispatch import receiver

from robots.signals import cloud_relays_wanted, ros2_discovery_wanted, ros_master_wanted

from .cloud.discovery import discovery_server_for
from .cloud.masters import ros_master_for
from .cloud.orchestration import enqueue_on_commit
from .cloud.relay import relays_for
from .models import Skill


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


@receiver(cloud_relays_wanted, dispatch_uid="skills-cloud-relays")
def provide_cloud_relays(sender: Any, robot_id: str, ros_master: str, **kw: Any) -> dict[str, dict[str, str]] | None:
    """Return {skill: {url, token}} of the cloud relays a connecting robot's Skills use (None: none)."""
    return relays_for(robot_id, ros_master) or None


@receiver(post_delete, sender=Skill, dispatch_uid="skills-cloud-relay-gone")
def stop_cloud_relay(sender: Any, instance: Skill, **kw: Any) -> None:
    """Stop a removed Skill's cloud relay (its row went with it) once the removal commits."""
    enqueue_on_commit("ensure_cloud_relay", instance.robot_id, instance.skill_id)
