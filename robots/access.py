"""Who may reach which robot: users' robots, API tokens and bridge tickets, checked at every door."""

from __future__ import annotations

import functools
from dataclasses import dataclass

from django.contrib.auth.models import AbstractBaseUser
from django.db import connection, transaction
from django.db.models import QuerySet
from django.utils import timezone

from .models import ApiToken, BridgeTicket, Robot, hash_token

API_TOKEN_PREFIX = "bat_"
BRIDGE_TICKET_PREFIX = "bbt_"


def visible_robots(user: AbstractBaseUser) -> QuerySet[Robot]:
    """Return the robots a user may see: their own, or all for staff."""
    robots = Robot.objects.all()
    return robots if user.is_staff else robots.filter(owner=user)


def visible_robot_ids(user: AbstractBaseUser) -> set[str] | None:
    """Return the ids of the robots a user may see, or None when they may see all."""
    return None if user.is_staff else set(visible_robots(user).values_list("id", flat=True))


def robot_scope(user: AbstractBaseUser) -> QuerySet[Robot] | None:
    """Return the robots a user's view is limited to, or None for staff (who also see fleet-wide records)."""
    return None if user.is_staff else visible_robots(user)


def can_see(user: AbstractBaseUser, robot_id: str) -> bool:
    """Tell whether a user may see and command a robot."""
    return visible_robots(user).filter(id=robot_id).exists()


def api_token(key: str) -> ApiToken | None:
    """Return the unexpired token with this key whose user is active, else None."""
    if not key.startswith(API_TOKEN_PREFIX):
        return None
    if connection.vendor == "postgresql":
        token = _api_token_by_hash(hash_token(key))
    else:
        token = ApiToken.objects.select_related("user").filter(key_hash=hash_token(key)).first()
    if token is None or token.expired or not token.user.is_active:
        return None
    return token


@functools.cache
def _api_token_query() -> tuple[str, list[str], list[str]]:
    """Return the SQL that reads a token with its user by key hash, and the field names of each part."""
    user = ApiToken._meta.get_field("user")
    user_model = user.related_model
    token_fields = [field.attname for field in ApiToken._meta.concrete_fields]
    user_fields = [field.attname for field in user_model._meta.concrete_fields]
    qn = connection.ops.quote_name
    columns = [f"t.{qn(field.column)}" for field in ApiToken._meta.concrete_fields]
    columns += [f"u.{qn(field.column)}" for field in user_model._meta.concrete_fields]
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
        connection.alias, user_fields, row[len(token_fields) :]
    )
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
    if ticket.expires_at <= timezone.now() or not user.is_active or not can_see(user, robot_id):
        return None
    return user


@dataclass(frozen=True)
class BridgeAccess:
    """Who opened a bridge to a robot, and the channel of the robot's connection ("" when offline)."""

    user_id: int
    robot_id: str
    channel: str


def open_bridge(robot_id: str, *, token: str | None = None, ticket: str | None = None) -> BridgeAccess | None:
    """Check a bridge client's API token or ticket for a robot; None when refused (the robot may not exist)."""
    user = None
    if token:
        found = api_token(token)
        user = found.user if found is not None and can_see(found.user, robot_id) else None
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
