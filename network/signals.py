"""Keep networks and certificates in step with robots, whichever door changed them."""

from __future__ import annotations

from typing import Any

from django.db.models.signals import post_save, pre_delete
from django.dispatch import receiver

from robots.models import Robot
from robots.signals import config_checked, credentials_rotated

from . import ipam, services


@receiver(post_save, sender=Robot, dispatch_uid="network-sync-config")
def allocate_on_save(sender: type[Robot], instance: Robot, created: bool, update_fields: Any = None, **kw: Any) -> None:
    """Give a new robot its subnets, and follow subnets changed in its config."""
    if created or update_fields is None or "config" in update_fields:
        services.sync_robot_config(instance)


@receiver(pre_delete, sender=Robot, dispatch_uid="network-revoke-on-delete")
def revoke_on_delete(sender: type[Robot], instance: Robot, **kw: Any) -> None:
    """A deleted robot's certificate goes on the CRL (its subnets go with it, by cascade)."""
    services.revoke_certificate(instance, "robot deleted")


@receiver(credentials_rotated, dispatch_uid="network-revoke-on-rotation")
def revoke_on_rotation(sender: Any, robot: Robot, **kw: Any) -> None:
    """New credentials: the old VPN certificate stops working too."""
    services.revoke_certificate(robot, "credentials rotated")


@receiver(config_checked, dispatch_uid="network-check-subnets")
def check_subnets(sender: type[Robot], robot_id: str, config: dict[str, Any], **kw: Any) -> None:
    """Refuse subnets in a robot config outside their pools or overlapping another robot's."""
    ipam.check_requested(robot_id, config)
