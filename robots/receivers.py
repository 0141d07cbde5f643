"""Keep writers that add a robot's rows without a foreign key off a robot being deleted."""

from __future__ import annotations

from typing import Any

from django.db.models.signals import pre_delete
from django.dispatch import receiver

from .models import Robot


@receiver(pre_delete, sender=Robot, dispatch_uid="robots-lock-before-delete")
def lock_before_delete(sender: type[Robot], instance: Robot, using: str, **kw: Any) -> None:
    """Lock a robot's row before its dependents are deleted, so no ingest batch commits points after them.

    Metric rows have no foreign key (monitoring.sinks): a batch that holds this robot's row commits
    before the lock is granted, and its points are then deleted with the others; a batch after it
    finds the robot gone. Django sends this inside the deletion's transaction, robots by primary key.
    """
    list(Robot.objects.using(using).select_for_update().filter(pk=instance.pk).values_list("pk", flat=True))
