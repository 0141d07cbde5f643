"""Domain actions on skills: adding a Skill config to a robot."""

from __future__ import annotations

from typing import Any

from django.core.exceptions import ValidationError
from django.db import transaction

from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_cloud.validation import validated_config
from monitoring.services import record_event
from robots.models import Robot

from .models import Component, Skill, SkillTemplate


def add_skill(robot: Robot, config: dict[str, Any]) -> Skill:
    """Add a Skill and its components to a robot, all or nothing."""
    normalised = validated_config(parse_skill_config, config)
    skill_id = normalised["skill_id"]
    with transaction.atomic():
        if Skill.objects.filter(robot=robot, skill_id=skill_id).exists():
            raise ValidationError({"skill_id": [f"Robot {robot.id} already has a skill {skill_id!r}."]})
        skill = Skill.objects.create(robot=robot, skill_id=skill_id, name=normalised["skill"], config=normalised)
        Component.objects.bulk_create(
            Component(
                skill=skill,
                component_id=component_id,
                location=component["location"],
                resources=component.get("resources", {}),
            )
            for component_id, component in normalised["components"].items()
        )
        record_event(f"Skill {skill_id} added", robot_id=robot.id, skill=skill_id, kind="skill_added")
    return skill


def add_skill_from_template(robot: Robot, template: SkillTemplate) -> Skill:
    """Add the Skill of a catalog template to a robot."""
    return add_skill(robot, template.config)
