"""Scoped API tokens: made by a member for one organization with a role at most theirs, listed, revoked."""

from __future__ import annotations

from datetime import datetime, timedelta
from typing import Any

from django.core.exceptions import ValidationError
from django.db import transaction
from django.db.models import QuerySet
from django.http import Http404
from django.utils import timezone

from robots.access import Actor
from robots.models import ApiToken
from robots.services import issue_api_token

from .models import Organization
from .roles import RANK, Right, Role
from .services import close_token_connections, role_named

MAX_EXPIRY_DAYS = 3650


def scoped_expiry(expires_at: datetime | None, expires_in_days: int | None) -> datetime | None:
    """Return a new token's expiry from an instant or a number of days (None: until revoked); 400 when past."""
    if expires_at is not None and expires_in_days is not None:
        raise ValidationError({"expires_at": ["Give expires_at or expires_in_days, not both."]})
    if expires_in_days is not None:
        if not 1 <= expires_in_days <= MAX_EXPIRY_DAYS:
            raise ValidationError({"expires_in_days": [f"Use 1 to {MAX_EXPIRY_DAYS} days."]})
        return timezone.now() + timedelta(days=expires_in_days)
    if expires_at is not None and expires_at <= timezone.now():
        raise ValidationError({"expires_at": ["Give an instant in the future."]})
    return expires_at


def make_token(
    actor: Actor,
    *,
    name: str,
    organization_slug: str,
    role: str,
    expires_at: datetime | None = None,
    expires_in_days: int | None = None,
) -> tuple[str, ApiToken]:
    """Issue the request's user a token for one of their organizations with a role at most theirs there.

    Return its key, shown only now, and the token. Another organization is refused exactly like
    a missing one, so the answer never tells which slugs exist.
    """
    if not name.strip():
        raise ValidationError({"name": ["Name the token, to know it again in the list."]})
    role = role_named(role)
    ids = actor.organization_ids()
    found = Organization.objects.filter(slug=organization_slug)
    organization = (found if ids is None else found.filter(id__in=ids)).first()
    if organization is None:
        raise ValidationError({"organization": ["No such organization of yours."]})
    yours = actor.role_in(organization.id)
    if yours is None or RANK[role] > RANK[Role(yours)]:
        raise ValidationError({"role": [f"A token's role may be at most yours here ({yours or 'none'})."]})
    when = scoped_expiry(expires_at, expires_in_days)
    return issue_api_token(actor.user, name=name, organization=organization, role=role, expires_at=when)


def token_scope(actor: Actor) -> int | None:
    """Return the organization a request's own token is held to (None: a login token or a session)."""
    return actor.token.organization_id if actor.token is not None else None


def tokens_of(actor: Actor) -> QuerySet[ApiToken]:
    """Return the request's user's API tokens, login ones too, newest first; a scoped token sees its organization's."""
    tokens = ApiToken.objects.filter(user=actor.user).select_related("organization", "user")
    scope = token_scope(actor)
    return (tokens if scope is None else tokens.filter(organization_id=scope)).order_by("-created_at", "-pk")


def organization_tokens(organization: Organization) -> QuerySet[ApiToken]:
    """Return the scoped tokens of an organization, newest first, with their users."""
    return organization.api_tokens.select_related("organization", "user").order_by("-created_at", "-pk")


def revoke_token(actor: Actor, token_id: int) -> None:
    """Delete a token of the request's user, or of an organization it administers, and close its connections.

    Any other token is a 404, as if it did not exist.
    """
    with transaction.atomic():
        token = ApiToken.objects.select_for_update().filter(pk=token_id).first()
        scope = token_scope(actor)
        allowed = (
            token is not None
            # A token held to one organization never reaches tokens of another (nor login tokens).
            and (scope is None or token.organization_id == scope)
            and (
                token.user_id == actor.user.pk
                or (token.organization_id is not None and actor.may(token.organization_id, Right.ADMINISTER))
            )
        )
        if not allowed or token is None:
            raise Http404("No such token.")
        close_token_connections([token.pk])
        token.delete()


def token_row(token: ApiToken) -> dict[str, Any]:
    """Return a token as the API and the dashboard list it (never its key: only its hash is kept)."""
    return {
        "id": token.pk,
        "name": token.name,
        "user": token.user.get_username(),
        "organization": token.organization.slug if token.organization else None,
        "role": token.role or None,
        "created_at": token.created_at,
        "expires_at": token.expires_at,
        "expired": token.expired,
    }
