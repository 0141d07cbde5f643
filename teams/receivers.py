"""Every user gets a personal organization when created; live connections follow changes of memberships and users."""

from __future__ import annotations

from typing import Any

from django.contrib.auth import get_user_model
from django.db.models.signals import post_delete, post_save
from django.dispatch import receiver

from . import services
from .models import Membership


@receiver(post_save, sender=get_user_model(), dispatch_uid="teams.personal_organization")
def give_personal_organization(sender: Any, instance: Any, created: bool, raw: bool = False, **kwargs: Any) -> None:
    """Make a new user's personal organization (not when loading fixtures)."""
    if created and not raw:
        services.personal_organization(instance)


@receiver(post_save, sender=Membership, dispatch_uid="teams.membership_saved")
@receiver(post_delete, sender=Membership, dispatch_uid="teams.membership_deleted")
def reload_member_connections(sender: Any, instance: Membership, raw: bool = False, **kwargs: Any) -> None:
    """Make the member's live connections reload their roles, whichever door changed the membership."""
    if not raw:
        services.reload_live_connections(instance.user_id)


@receiver(post_save, sender=get_user_model(), dispatch_uid="teams.user_saved")
@receiver(post_delete, sender=get_user_model(), dispatch_uid="teams.user_deleted")
def reload_user_connections(sender: Any, instance: Any, raw: bool = False, **kwargs: Any) -> None:
    """Make a changed or deleted user's live connections reload, so a deactivated one's close and staff's follow."""
    created, fields = kwargs.get("created", False), kwargs.get("update_fields")
    # Every login saves last_login: nothing a live connection acts on.
    if raw or created or (fields is not None and set(fields) <= {"last_login"}):
        return
    services.reload_live_connections(instance.pk)
