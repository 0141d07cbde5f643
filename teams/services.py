"""Domain actions on organizations: personal ones, team ones, members and their roles."""

from __future__ import annotations

from typing import Any

from channels.layers import get_channel_layer
from django.contrib.auth import get_user_model
from django.contrib.auth.models import AbstractBaseUser
from django.core.exceptions import ValidationError
from django.db import IntegrityError, transaction
from django.db.models import Q
from django.http import Http404

from bridgeos_cloud.layersync import layer_sync
from robots import access
from robots.access import Actor
from robots.models import ApiToken

from .models import Membership, Organization, slug_validator
from .naming import personal_slug
from .roles import RANK, Right, Role

# One body for another organization's and a missing one, so an answer never tells which exists.
NO_SUCH_ORGANIZATION = "No such organization."
LAST_ADMIN = "An organization needs at least one admin: make another member admin first."


def personal_organization(user: AbstractBaseUser) -> Organization:
    """Return the user's personal organization, making it (with them as admin) if it does not exist yet."""
    found = Organization.objects.filter(personal_of=user).first()
    if found is not None:
        return found
    with transaction.atomic():
        slug = personal_slug(user.get_username(), user.pk, lambda s: Organization.objects.filter(slug=s).exists())
        organization = Organization.objects.create(slug=slug, name=user.get_username(), personal_of=user)
        Membership.objects.create(organization=organization, user=user, role=Role.ADMIN)
    return organization


def reachable_organizations(actor: Actor) -> list[tuple[Organization, str | None]]:
    """Return the organizations a request reaches, each with the role it acts with there (staff: every one)."""
    ids = actor.organization_ids()
    found = Organization.objects.all() if ids is None else Organization.objects.filter(id__in=ids)
    return [(organization, actor.role_in(organization.id)) for organization in found.order_by("slug")]


def organization_for(actor: Actor, slug: str, right: Right = Right.READ) -> Organization:
    """Return an organization the request holds a right in; 404 if it does not reach it, 403 if its role falls short."""
    ids = actor.organization_ids()
    found = Organization.objects.filter(slug=slug)
    organization = (found if ids is None else found.filter(id__in=ids)).first()
    if organization is None:
        raise Http404(NO_SUCH_ORGANIZATION)
    access.require(actor, organization.id, right)
    return organization


def create_organization(user: AbstractBaseUser, slug: str, name: str = "") -> Organization:
    """Make a team organization with its creator as admin; refuse a bad, taken or another user's slug."""
    try:
        slug_validator(slug)
    except ValidationError as exc:
        raise ValidationError({"slug": exc.messages}) from exc
    if len(slug) > Organization._meta.get_field("slug").max_length:
        raise ValidationError({"slug": ["Use at most 64 characters."]})
    # Slugs name registry namespaces, where a user's name was theirs before organizations existed.
    other_user = get_user_model().objects.filter(username__iexact=slug).exclude(pk=user.pk).exists()
    if other_user or Organization.objects.filter(slug=slug).exists():
        raise ValidationError({"slug": ["This slug is taken."]})
    try:
        with transaction.atomic():
            organization = Organization.objects.create(slug=slug, name=name or slug)
            Membership.objects.create(organization=organization, user=user, role=Role.ADMIN)
    except IntegrityError as exc:  # taken by a request that raced this one
        raise ValidationError({"slug": ["This slug is taken."]}) from exc
    return organization


def members(organization: Organization) -> list[Membership]:
    """Return an organization's memberships with their users, by username."""
    return list(organization.memberships.select_related("user").order_by("user__username"))


def role_named(value: str) -> Role:
    """Return the role a request names; a 400 on ``role`` when it names none."""
    if value not in Role.values:
        raise ValidationError({"role": [f"Use one of {', '.join(Role.values)}."]})
    return Role(value)


def member_user(username: str) -> AbstractBaseUser:
    """Return the active user with this username; a 400 on ``username`` when there is none."""
    user = get_user_model().objects.filter(username=username, is_active=True).first()
    if user is None:
        raise ValidationError({"username": ["No such user."]})
    return user


def add_member(organization: Organization, username: str, role: str) -> Membership:
    """Make a user a member with a role; a 400 when they already are one."""
    user = member_user(username)
    role_named(role)
    with transaction.atomic():
        if Membership.objects.filter(organization=organization, user=user).exists():
            raise ValidationError({"username": ["Already a member; change their role instead."]})
        return Membership.objects.create(organization=organization, user=user, role=role_named(role))


def membership_of(organization: Organization, username: str) -> Membership:
    """Return a member's membership for a change, with the organization locked; 404 when they are not a member.

    Every change of members locks the organization's row first, so two admins changing two
    members at once take turns rather than deadlock on each other's rows, and the last-admin
    rule sees the other's change.
    """
    Organization.objects.select_for_update().filter(pk=organization.pk).first()
    found = (
        Membership.objects.select_for_update()
        .select_related("user")
        .filter(organization=organization, user__username=username)
        .first()
    )
    if found is None:
        raise Http404("No such member.")
    return found


def _keep_an_admin(organization: Organization, leaving: Membership) -> None:
    """Refuse a change that would leave an organization without an admin (the organization is locked)."""
    admins = list(Membership.objects.filter(organization=organization, role=Role.ADMIN).values_list("pk", flat=True))
    if leaving.role == Role.ADMIN and admins == [leaving.pk]:
        raise ValidationError({"role": [LAST_ADMIN]})


def change_role(organization: Organization, username: str, role: str) -> Membership:
    """Give a member another role; their scoped tokens there are capped to it and their live connections closed.

    A lowered token's cap is not raised again if the member's role later is: a token never does
    more than it was made for, nor more than its user may now.
    """
    role = role_named(role)
    with transaction.atomic():
        membership = membership_of(organization, username)
        if role != Role.ADMIN:
            _keep_an_admin(organization, membership)
        lowered = RANK[role] < RANK[Role(membership.role)]
        membership.role = role
        membership.save(update_fields=["role"])
        if lowered:
            tokens = ApiToken.objects.filter(user=membership.user, organization=organization)
            above = [t.pk for t in tokens.exclude(role="") if RANK[Role(t.role)] > RANK[role]]
            tokens.filter(pk__in=above).update(role=role)
            tokens.filter(role="").update(role=role)
            # A live connection loaded the member's roles when it opened: it reopens with the new one.
            close_token_connections(live_tokens(membership))
    return membership


def remove_member(organization: Organization, username: str) -> None:
    """End a membership; the member's tokens of that organization are deleted and their connections closed."""
    with transaction.atomic():
        membership = membership_of(organization, username)
        _keep_an_admin(organization, membership)
        close_token_connections(live_tokens(membership))
        ApiToken.objects.filter(user=membership.user, organization=organization).delete()
        membership.delete()


def live_tokens(membership: Membership) -> list[int]:
    """Return the member's tokens whose connections hold their role there: that organization's, and login ones."""
    tokens = ApiToken.objects.filter(user_id=membership.user_id)
    scoped = Q(organization_id=membership.organization_id) | Q(organization=None)
    return list(tokens.filter(scoped).values_list("pk", flat=True))


def close_token_connections(token_ids: list[int]) -> None:
    """Close the live /ws/client/ connections of API tokens once the change that ended them commits."""
    if not token_ids:
        return
    send = layer_sync(get_channel_layer().group_send)

    def close() -> None:
        for token_id in token_ids:
            send(access.token_group(token_id), {"type": "token.revoked"})

    transaction.on_commit(close, robust=True)


def reload_live_connections(user_id: int) -> None:
    """Make a user's live /ws/client/ connections reload their roles, once the change to them commits.

    A connection loads its roles when it opens; after a membership is added, changed or ended, or
    the account itself changed, each reloads them, or closes when it may no longer act.
    """
    send = layer_sync(get_channel_layer().group_send)
    transaction.on_commit(lambda: send(access.user_group(user_id), {"type": "membership.changed"}), robust=True)


def member_row(membership: Membership) -> dict[str, Any]:
    """Return a membership as the API and the dashboard show it."""
    return {"username": membership.user.get_username(), "role": membership.role, "since": membership.created_at}
