"""Who may reach which robot: members' roles in its organization, API tokens and bridge tickets, at every door."""

from __future__ import annotations

import functools
import json
from dataclasses import dataclass, field
from typing import Any

from django.contrib.auth import get_user_model
from django.contrib.auth.models import AbstractBaseUser
from django.db import connection, transaction
from django.db.models import QuerySet
from django.http import Http404
from django.utils import timezone
from rest_framework.exceptions import PermissionDenied

from teams.models import Membership
from teams.roles import Right, Role, holds, lesser

from .models import ApiToken, BridgeTicket, Robot, hash_token

API_TOKEN_PREFIX = "bat_"
BRIDGE_TICKET_PREFIX = "bbt_"


@dataclass
class Actor:
    """Who makes a request: a user, held to one organization and a role when their token or session says so."""

    user: AbstractBaseUser
    # The one organization this request may act in (a scoped token's, a session's pick); None: all of the user's.
    organization_id: int | None = None
    # The most this request may do there (a scoped token's role); None: the user's own role.
    role_cap: str | None = None
    token: ApiToken | None = None
    # The user's role in each organization, keyed by its id; loaded once, when first needed.
    memberships: dict[int, str] | None = field(default=None, repr=False)

    @property
    def everywhere(self) -> bool:
        """Tell whether this request reaches every organization (staff, unless scoped)."""
        return bool(self.user.is_staff) and self.organization_id is None

    def roles(self) -> dict[int, str]:
        """Return the user's own role in each of their organizations."""
        if self.memberships is None:
            rows = Membership.objects.filter(user_id=self.user.pk).values_list("organization_id", "role")
            self.memberships = dict(rows)
        return self.memberships

    def role_in(self, organization_id: int) -> str | None:
        """Return the role this request acts with in an organization; None when it has none there."""
        if self.organization_id is not None and organization_id != self.organization_id:
            return None
        role = Role.ADMIN if self.user.is_staff else self.roles().get(organization_id)
        return None if role is None else lesser(role, self.role_cap)

    def organization_ids(self) -> list[int] | None:
        """Return the organizations this request reaches, or None for every one."""
        if self.everywhere:
            return None
        if self.organization_id is not None:
            return [self.organization_id] if self.role_in(self.organization_id) else []
        return list(self.roles())

    def may(self, organization_id: int, right: Right) -> bool:
        """Tell whether this request holds a right in an organization."""
        return holds(self.role_in(organization_id), right)


Who = Actor | AbstractBaseUser


def as_actor(who: Who) -> Actor:
    """Return an actor for a user acting with all their roles, or the actor itself."""
    return who if isinstance(who, Actor) else Actor(who)


def actor_of(request: Any) -> Actor:
    """Return who makes a request: its API token's scope, else the session's picked organization, else the user."""
    cached = getattr(request, "_bridgeos_actor", None)
    if cached is not None and cached.user is request.user:
        return cached
    token = getattr(request, "auth", None)
    if isinstance(token, ApiToken):
        actor = token_actor(token)
    else:
        session = getattr(request, "session", None)
        picked = session.get(SESSION_ORGANIZATION) if session is not None else None
        actor = Actor(request.user, organization_id=picked)
    request._bridgeos_actor = actor
    return actor


SESSION_ORGANIZATION = "bridgeos_organization"


def token_actor(token: ApiToken) -> Actor:
    """Return the actor an API token makes: its user, limited to its organization and role if it names them."""
    return Actor(
        token.user,
        organization_id=token.organization_id,
        role_cap=token.role or None,
        token=token,
        memberships=getattr(token, "memberships", None),
    )


def token_group(token_id: int) -> str:
    """Name the channel group of the live connections an API token opened, closed when it is revoked."""
    return f"api-token-{token_id}"


def user_group(user_id: int) -> str:
    """Name the channel group of a user's live connections, told when their memberships or account change."""
    return f"user-{user_id}"


def current_actor(actor: Actor) -> Actor | None:
    """Return a live connection's actor read afresh: its token, account and roles now; None when it may no longer act.

    A session held to one organization may no longer act once its user is not a member there,
    as a scoped token is deleted with its user's membership.
    """
    if actor.token is not None:
        token = _usable_token(actor.token.key_hash)
        return None if token is None else token_actor(token)
    user = get_user_model().objects.filter(pk=actor.user.pk).first()
    if user is None or not user.is_active:
        return None
    fresh = Actor(user, organization_id=actor.organization_id)
    roles = fresh.roles()
    if fresh.organization_id is not None and not user.is_staff and fresh.organization_id not in roles:
        return None
    return fresh


def visible_robots(who: Who) -> QuerySet[Robot]:
    """Return the robots a request may see: those of its organizations, or all for staff."""
    ids = as_actor(who).organization_ids()
    robots = Robot.objects.all()
    if ids is None:
        return robots
    return robots.filter(organization_id=ids[0]) if len(ids) == 1 else robots.filter(organization_id__in=ids)


def robots_with(who: Who, right: Right) -> QuerySet[Robot]:
    """Return the robots a request holds a right on."""
    actor = as_actor(who)
    if actor.everywhere:
        return Robot.objects.all()
    ids = [org for org in actor.organization_ids() or [] if actor.may(org, right)]
    return Robot.objects.filter(organization_id__in=ids)


def visible_robot_ids(who: Who) -> set[str] | None:
    """Return the ids of the robots a request may see, or None when it may see all."""
    actor = as_actor(who)
    return None if actor.everywhere else set(visible_robots(actor).values_list("id", flat=True))


def robot_scope(who: Who) -> QuerySet[Robot] | None:
    """Return the robots a request's view is limited to, or None for staff (who also see fleet-wide records)."""
    actor = as_actor(who)
    return None if actor.everywhere else visible_robots(actor)


def can_see(who: Who, robot_id: str) -> bool:
    """Tell whether a request may see a robot."""
    return visible_robots(who).filter(id=robot_id).exists()


def may_on_robot(who: Who, robot_id: str, right: Right) -> bool | None:
    """Tell whether a request holds a right on a robot; None when it may not even see it (or it does not exist)."""
    actor = as_actor(who)
    organization_id = Robot.objects.filter(id=robot_id).values_list("organization_id", flat=True).first()
    if organization_id is None or (not actor.everywhere and actor.role_in(organization_id) is None):
        return None
    return actor.may(organization_id, right)


def robot_for(who: Who, robot_id: str, right: Right = Right.READ) -> Robot:
    """Return a robot the request holds a right on; 404 if it may not see it, 403 if its role falls short.

    Another organization's robot and a robot that does not exist take the same query and get
    the same answer, so neither the body nor the time tells whether it exists.
    """
    actor = as_actor(who)
    # Read by id, then judged here: cheaper than filtering by the actor's organizations in SQL.
    robot = Robot.objects.filter(id=robot_id).first()
    if robot is None or (not actor.everywhere and actor.role_in(robot.organization_id) is None):
        raise Http404("No Robot matches the given query.")
    require(actor, robot.organization_id, right)
    return robot


def require(who: Who, organization_id: int, right: Right) -> None:
    """Raise a 403 naming the role a right needs when the request lacks it in an organization."""
    actor = as_actor(who)
    if not actor.may(organization_id, right):
        role = actor.role_in(organization_id)
        needed = {Right.READ: "viewer", Right.COMMAND: "operator", Right.DEVELOP: "developer"}.get(right, "admin")
        yours = f"your role here is {role}" if role else "you have no role here"
        raise PermissionDenied(f"This needs the {needed} role in the robot's organization; {yours}.")


def api_token(key: str) -> ApiToken | None:
    """Return the unexpired token with this key whose user is active, else None."""
    if not key.startswith(API_TOKEN_PREFIX):
        return None
    return _usable_token(hash_token(key))


def _usable_token(key_hash: str) -> ApiToken | None:
    """Return the unexpired token with this key hash whose user is active and still a member of its scope, else None."""
    if connection.vendor == "postgresql":
        token = _api_token_by_hash(key_hash)
    else:
        token = ApiToken.objects.select_related("user").filter(key_hash=key_hash).first()
    if token is None or token.expired or not token.user.is_active:
        return None
    if connection.vendor != "postgresql":
        token.memberships = dict(
            Membership.objects.filter(user_id=token.user_id).values_list("organization_id", "role")
        )
    # A scoped token never outlives its user's membership of its organization (staff need none).
    if token.organization_id is not None and not token.user.is_staff and token.organization_id not in token.memberships:
        return None
    return token


@functools.cache
def _api_token_query() -> tuple[str, list[str], list[str]]:
    """Return the SQL that reads a token with its user and the user's roles by key hash, and each part's fields."""
    user = ApiToken._meta.get_field("user")
    user_model = user.related_model
    token_fields = [field.attname for field in ApiToken._meta.concrete_fields]
    user_fields = [field.attname for field in user_model._meta.concrete_fields]
    qn = connection.ops.quote_name
    columns = [f"t.{qn(field.column)}" for field in ApiToken._meta.concrete_fields]
    columns += [f"u.{qn(field.column)}" for field in user_model._meta.concrete_fields]
    columns.append(
        f"(SELECT json_object_agg(m.organization_id, m.role) FROM {qn(Membership._meta.db_table)} m"
        f" WHERE m.user_id = u.{qn(user_model._meta.pk.column)})"
    )
    sql = (
        f"SELECT {', '.join(columns)} FROM {qn(ApiToken._meta.db_table)} t"
        f" JOIN {qn(user_model._meta.db_table)} u ON u.{qn(user_model._meta.pk.column)} = t.{qn(user.column)}"
        f" WHERE t.{qn(ApiToken._meta.get_field('key_hash').column)} = %s"
    )
    return sql, token_fields, user_fields


def _api_token_by_hash(key_hash: str) -> ApiToken | None:
    """Return the token with this key hash and its user, in one query compiled once per process.

    Every API request authenticates: building this query through the ORM each time (a join,
    an ordering, model instances) was the largest share of a read's CPU under load.
    """
    sql, token_fields, user_fields = _api_token_query()
    with connection.cursor() as cursor:
        cursor.execute(sql, [key_hash])
        row = cursor.fetchone()
    if row is None:
        return None
    token = ApiToken.from_db(connection.alias, token_fields, row[: len(token_fields)])
    token.user = ApiToken._meta.get_field("user").related_model.from_db(
        connection.alias, user_fields, row[len(token_fields) : -1]
    )
    roles = row[-1]
    if isinstance(roles, str):  # a driver that leaves json as text
        roles = json.loads(roles)
    token.memberships = {int(org): role for org, role in (roles or {}).items()}
    return token


def redeem_bridge_ticket(key: str, robot_id: str) -> AbstractBaseUser | None:
    """Spend a ticket for a robot: return its user if it was unexpired, unused, for this robot and still allowed."""
    if not key.startswith(BRIDGE_TICKET_PREFIX) or len(key) > 100:
        return None
    with transaction.atomic():
        ticket = (
            BridgeTicket.objects.select_for_update()
            .select_related("user")
            .filter(key_hash=hash_token(key), robot_id=robot_id)
            .first()
        )
        if ticket is None:
            return None
        ticket.delete()  # used once, even when it turns out expired
    user = ticket.user
    if ticket.expires_at <= timezone.now() or not user.is_active or not may_on_robot(user, robot_id, Right.COMMAND):
        return None
    return user


@dataclass(frozen=True)
class BridgeAccess:
    """Who opened a bridge to a robot, and the channel of the robot's connection ("" when offline)."""

    user_id: int
    robot_id: str
    channel: str


def open_bridge(robot_id: str, *, token: str | None = None, ticket: str | None = None) -> BridgeAccess | None:
    """Check a bridge client's API token or ticket for a robot (an operator's right); None when refused.

    A bridge publishes and calls services on the robot, so a viewer may not open one; refused
    for any reason, including a robot that does not exist, the client learns only that.
    """
    user = None
    if token:
        found = api_token(token)
        user = found.user if found is not None and may_on_robot(token_actor(found), robot_id, Right.COMMAND) else None
    elif ticket:
        user = redeem_bridge_ticket(ticket, robot_id)
    if user is None:
        return None
    row = Robot.objects.filter(id=robot_id).values_list("connected", "channel").first()
    if row is None:
        return None
    connected, channel = row
    return BridgeAccess(user.pk, robot_id, channel if connected else "")


def authenticate_api_token(key: str) -> AbstractBaseUser | None:
    """Return the active user an unexpired API token belongs to, else None."""
    token = api_token(key)
    return None if token is None else token.user
