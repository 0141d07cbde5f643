"""Name the ROS namespaces the Skill Router gives each component instance (thesis §3.4.2)."""

from __future__ import annotations

from typing import Literal

__all__ = ["NAMESPACE_ROOT", "canonical_name", "graph_segment", "instance_name", "instance_namespace"]

NAMESPACE_ROOT = "/bridgeos"


def graph_segment(slug: str) -> str:
    """Return a Skill or component id as a valid ROS graph name segment (``people-detection`` → ``people_detection``).

    Ids may hold hyphens and start with a digit; roscpp refuses both in graph names (rospy is
    laxer), so hyphens become underscores and a leading digit gets an ``n`` before it.
    """
    segment = slug.replace("-", "_")
    return f"n{segment}" if segment[:1].isdigit() else segment


def instance_namespace(skill: str, component: str, location: Literal["robot", "cloud"]) -> str:
    """Return the namespace one instance of a component runs in (its ``ROS_NAMESPACE``)."""
    if location not in ("robot", "cloud"):
        raise ValueError(f"location must be 'robot' or 'cloud', not {location!r}")
    return f"{NAMESPACE_ROOT}/{graph_segment(skill)}/{graph_segment(component)}/{location}"


def canonical_name(name: str) -> str:
    """Return a graph name as the absolute name peers use (``scan`` → ``/scan``)."""
    return name if name.startswith("/") else f"/{name}"


def instance_name(name: str, skill: str, component: str, location: Literal["robot", "cloud"]) -> str:
    """Return where a component instance's own ``name`` lands inside its namespace."""
    return instance_namespace(skill, component, location) + canonical_name(name)
