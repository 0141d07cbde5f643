"""Choices of skill and component fields, taken from the shared protocol."""

from __future__ import annotations

from bridgeos_agent.protocol import ComponentStatusName, Location, SkillStatusName


def _choices(enum: type) -> list[tuple[str, str]]:
    return [(member.value, member.value.replace("_", " ").capitalize()) for member in enum]


LOCATION_CHOICES = _choices(Location)
ACTIVE_LOCATION_CHOICES = [(value, label) for value, label in LOCATION_CHOICES if value != "either"]
SKILL_STATUS_CHOICES = _choices(SkillStatusName)
COMPONENT_STATUS_CHOICES = _choices(ComponentStatusName)
