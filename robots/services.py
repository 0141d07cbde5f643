"""Domain actions on robots: creation and credentials."""

from __future__ import annotations

from typing import Any

from django.contrib.auth.models import AbstractBaseUser
from django.db import transaction

from monitoring.services import record_event

from .models import Robot


def create_robot(
    robot_id: str, owner: AbstractBaseUser, *, name: str = "", config: dict[str, Any] | None = None
) -> tuple[Robot, str]:
    """Create a robot and return it with its token, which is shown this once."""
    robot = Robot(id=robot_id, owner=owner, name=name)
    if config is not None:
        robot.config = config
    token = robot.issue_token()
    robot.full_clean()
    with transaction.atomic():
        robot.save(force_insert=True)
        record_event(f"Robot {robot_id} created", robot_id=robot_id, kind="robot_created")
    return robot, token


def rotate_token(robot: Robot) -> str:
    """Give a robot a new token, invalidating the old one, and return it."""
    token = robot.issue_token()
    with transaction.atomic():
        robot.save(update_fields=["token_hash"])
        record_event(f"Token of robot {robot.id} rotated", robot_id=robot.id, kind="robot_token_rotated")
    return token
