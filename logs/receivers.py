"""Follow what happens to robots: a deleted robot's lines go with it."""

from __future__ import annotations

from typing import Any

from django.db import transaction
from django.db.models.signals import post_delete
from django.dispatch import receiver

from robots.models import Robot

from .services import forget_robot


@receiver(post_delete, sender=Robot, dispatch_uid="logs-forget-robot")
def forget_deleted_robot(sender: Any, instance: Robot, **kw: Any) -> None:
    """Delete a deleted robot's lines (its id may later name another owner's robot)."""
    robot_id = instance.pk
    transaction.on_commit(lambda: forget_robot(robot_id), robust=True)
