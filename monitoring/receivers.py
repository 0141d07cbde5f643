"""Log in the event log what lower layers announce by signal, and keep ingest off a robot being deleted."""

from __future__ import annotations

from typing import Any

from django.db.models.signals import pre_delete
from django.dispatch import receiver

from bridgeos_cloud.bruteforce import login_blocked
from robots.models import Robot

from .choices import Level
from .services import record_event


@receiver(login_blocked, dispatch_uid="monitoring-login-blocked")
def log_login_blocked(sender: Any, scope: str, identity: str, address: str, **kw: Any) -> None:
    """Record that an identity is blocked after too many failed logins."""
    record_event(
        f"Too many failed authentications of {scope} {identity[:150]} from {address}",
        level=Level.WARNING,
        kind="authentication_blocked",
        data={scope: identity[:150], "address": address},
    )


@receiver(pre_delete, sender=Robot, dispatch_uid="monitoring-hold-ingest-off")
def hold_ingest_off(sender: type[Robot], instance: Robot, using: str, **kw: Any) -> None:
    """Lock a robot's row before its points are deleted, so no ingest batch commits points after them.

    Metric rows have no foreign key (monitoring.sinks): a batch holding this robot's row commits
    before the lock is granted, and its points are then deleted with the others; a batch after
    finds the robot gone. Django sends this inside the deletion's transaction, robots by primary key.
    """
    list(Robot.objects.using(using).select_for_update().filter(pk=instance.pk).values_list("pk", flat=True))
