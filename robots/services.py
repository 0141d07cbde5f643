"""Domain actions on robots: creation, credentials, connections and commands (who may reach which robot: access.py)."""

from __future__ import annotations

import json
import secrets
import time
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any, Literal

from channels.layers import get_channel_layer
from django.conf import settings
from django.contrib.auth.models import AbstractBaseUser
from django.db import connection, transaction
from django.db.models import Q
from django.utils import timezone
from pydantic_core import from_json

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Event
from bridgeos_agent.robotconfig import merge_config_changes
from bridgeos_cloud import bruteforce
from bridgeos_cloud.layersync import layer_sync
from monitoring import prometheus
from monitoring.choices import Level
from monitoring.live import publish_all_on_commit, publish_on_commit
from monitoring.services import record_event, record_events
from teams.models import Organization
from teams.services import personal_organization

from .access import API_TOKEN_PREFIX, BRIDGE_TICKET_PREFIX
from .choices import RobotStatus
from .models import ApiToken, BridgeTicket, Robot, hash_token, token_matches
from .relay import CommandTimeout, RobotOffline, relay_command, relay_to_many  # noqa: F401 (the API of this module)
from .rotation import revoke_on_commit
from .signals import cloud_relays_wanted, ros2_discovery_wanted, ros_master_wanted


def create_robot(
    robot_id: str,
    owner: AbstractBaseUser,
    *,
    name: str = "",
    config: dict[str, Any] | None = None,
    organization: Organization | None = None,
    labels: dict[str, str] | None = None,
) -> tuple[Robot, str]:
    """Create a robot in an organization (default: the owner's personal one); return it with its token, shown once."""
    organization = organization or personal_organization(owner)
    robot = Robot(id=robot_id, owner=owner, name=name, organization=organization, labels=labels or {})
    if config is not None:
        robot.config = config
    token = robot.issue_token()
    robot.full_clean()
    with transaction.atomic():
        robot.save(force_insert=True)
        record_event(f"Robot {robot_id} created", robot_id=robot_id, kind="robot_created")
    return robot, token


# --------------------------------------------------------------------------- connections


def authenticate_robot(robot_id: str, token: str) -> Robot | None:
    """Return the robot whose id and token match, else None."""
    robot = Robot.objects.filter(id=robot_id).first()
    if robot is None:
        # Hash anyway so a wrong id costs the same time as a wrong token.
        hash_token(token)
        return None
    return robot if robot.check_token(token) else None


class LoginBlocked(Exception):
    """Too many failed logins of this robot from this address: refused for ``retry_s`` seconds more."""

    def __init__(self, retry_s: float) -> None:
        super().__init__(f"too many failed attempts; try again in {retry_s:g} s")
        self.retry_s = retry_s


def login_robot(robot_id: str, token: str, address: str) -> Robot | None:
    """Check a robot's token presented from an address, counting failures; raise LoginBlocked past the limit."""
    retry = bruteforce.blocked("robot", robot_id, address)
    if retry:
        raise LoginBlocked(retry)
    robot = authenticate_robot(robot_id, token)
    bruteforce.attempted("robot", robot_id, address, robot is not None)
    return robot


@dataclass(frozen=True)
class Login:
    """A robot presenting its token on a consumer channel, from an address."""

    robot_id: str
    token: str
    address: str
    channel: str
    ros_master: str | None = None
    # The robot's ROS 2 graph (protocol.Ros2GraphInfo as JSON data), when its agent runs ROS 2.
    ros2: dict[str, Any] | None = None
    # Labels its agent asks for (already valid): applied only while the robot has none.
    labels: dict[str, str] | None = None


@dataclass
class Connected:
    """What became of a Login: refused (``robot`` None, maybe ``blocked_s``) or connected."""

    robot: str | None = None
    blocked_s: float = 0.0
    config: dict[str, Any] = field(default_factory=dict)
    replaced_channel: str = ""
    ros_master: str | None = None
    ros2_discovery_server: str | None = None
    cloud_relays: dict[str, dict[str, str]] | None = None


def connect_robots(logins: list[Login]) -> list[Connected]:
    """Check many robots' tokens and mark the good ones connected, in a few round trips for them all.

    The same checks as ``login_robot`` (brute-force limits, each robot's hashed token compared in
    constant time), then the robots are marked connected with their events: one Redis pipeline,
    two SELECTs, one UPDATE and one INSERT of events per batch, so a connect storm is not a queue
    of round trips per robot. The robots of one batch must be distinct.
    """
    outcomes = [Connected() for _ in logins]
    retries = bruteforce.blocked_many("robot", [(login.robot_id, login.address) for login in logins])
    for outcome, retry in zip(outcomes, retries, strict=True):
        outcome.blocked_s = retry
    candidates = [i for i, retry in enumerate(retries) if not retry]
    hashes = _token_hashes([logins[i].robot_id for i in candidates])
    proven = []
    for i in candidates:
        # Hashed even for an unknown robot, so a wrong id costs the same time as a wrong token.
        current, previous, until = hashes.get(logins[i].robot_id, ("", "", None))
        if token_matches(current, previous, until, logins[i].token):
            proven.append(i)
    good = set(proven)
    bruteforce.attempted_many("robot", [(logins[i].robot_id, logins[i].address, i in good) for i in candidates])
    if proven:
        _mark_all_connected([logins[i] for i in proven], [outcomes[i] for i in proven])
    return outcomes


def _token_hashes(robot_ids: list[str]) -> dict[str, tuple[str, str, datetime | None]]:
    """Return the robots' current and previous token hashes, and when the previous one stops working."""
    if connection.vendor != "postgresql":
        rows = Robot.objects.filter(id__in=robot_ids).values_list(
            "id", "token_hash", "previous_token_hash", "previous_token_until"
        )
        return {robot_id: (current, previous, until) for robot_id, current, previous, until in rows}
    # One array parameter, as _lock_for_logins reads: for 500 robots the ORM's IN (...) and its row
    # conversion cost this thread, which shares daphne's interpreter, 3.5 ms of CPU, this 1.1 ms (measured).
    table = connection.ops.quote_name(Robot._meta.db_table)
    with connection.cursor() as cursor:
        cursor.execute(
            f"SELECT id, token_hash, previous_token_hash, previous_token_until FROM {table} WHERE id = ANY(%s)",
            [robot_ids],
        )
        return {robot_id: (current, previous, until) for robot_id, current, previous, until in cursor.fetchall()}


@dataclass
class LoginRow:
    """What a login reads of a robot's row and writes back: its row stays locked until the login commits."""

    id: str
    connected: bool
    channel: str
    ros2: dict[str, Any] | None
    labels: dict[str, str]
    config: dict[str, Any]
    ros_master: str = ""


def _lock_for_logins(robot_ids: list[str]) -> dict[str, LoginRow]:
    """Lock the robots' rows in id order, so two batches (of two processes) never deadlock; read what a login needs.

    FOR NO KEY UPDATE, as the login's UPDATE itself takes: it waits for a deletion or another login
    of the robot, never for an ingest batch's FOR KEY SHARE. On PostgreSQL one query with one array
    parameter, its rows decoded here: this thread shares daphne's interpreter, and for 500 robots
    the ORM's ``IN (...)`` and model instances cost it 12-20 ms of CPU, this query 1.3 ms before
    its JSON columns are decoded (measured).
    """
    if connection.vendor != "postgresql":
        robots = Robot.objects.select_for_update().filter(id__in=robot_ids).order_by("id")
        return {
            robot.id: LoginRow(robot.id, robot.connected, robot.channel, robot.ros2, robot.labels, robot.config)
            for robot in robots.only("id", "connected", "channel", "ros2", "labels", "config")
        }
    table = connection.ops.quote_name(Robot._meta.db_table)
    with connection.cursor() as cursor:
        cursor.execute(
            f"SELECT id, connected, channel, ros2, labels, config FROM {table}"
            f" WHERE id = ANY(%s) ORDER BY id FOR NO KEY UPDATE",
            [robot_ids],
        )
        rows = cursor.fetchall()
    return {
        robot_id: LoginRow(robot_id, connected, channel, _json(ros2), _json(labels) or {}, _json(config))
        for robot_id, connected, channel, ros2, labels, config in rows
    }


def _json(value: Any) -> Any:
    """Return a jsonb column's value as Python: Django's PostgreSQL backend hands raw queries its text."""
    if not isinstance(value, str):
        return value
    try:
        # pydantic's parser (Rust) reads a robot's config in a third of json.loads's time: 3 us, not 9.
        return from_json(value)
    except ValueError:
        return json.loads(value)  # it is stricter about escapes (a lone surrogate): json decides


def _mark_all_connected(logins: list[Login], outcomes: list[Connected]) -> None:
    """Record that robots connected on their channels, filling in each one's config and ROS master."""
    now = timezone.now()
    with transaction.atomic():
        robots = _lock_for_logins([login.robot_id for login in logins])
        changed: list[LoginRow] = []
        events: list[dict[str, Any]] = []
        frames: list[tuple[str | None, dict[str, Any]]] = []
        for login, outcome in zip(logins, outcomes, strict=True):
            robot = robots.get(login.robot_id)
            if robot is None:
                continue  # deleted since its token was checked
            reported = login.ros_master
            answers = [answer for _, answer in ros_master_wanted.send(Robot, robot_id=robot.id, reported=reported)]
            master = next((answer for answer in answers if answer is not None), reported or "")
            outcome.robot, outcome.config, outcome.ros_master = robot.id, robot.config, master or None
            servers = ros2_discovery_wanted.send(Robot, robot_id=robot.id, graph=login.ros2, previous=robot.ros2)
            outcome.ros2_discovery_server = next((answer for _, answer in servers if answer), None)
            relays = cloud_relays_wanted.send(Robot, robot_id=robot.id, ros_master=master)
            outcome.cloud_relays = next((answer for _, answer in relays if answer), None)
            # Kept with the graph, so the API and the dashboard show where its cloud copies find each other.
            robot.ros2 = (
                None if login.ros2 is None else {**login.ros2, "cloud_discovery_server": outcome.ros2_discovery_server}
            )
            outcome.replaced_channel = robot.channel if robot.connected and robot.channel != login.channel else ""
            robot.channel, robot.ros_master = login.channel, master
            changed.append(robot)
            events.append(
                {"message": f"Robot {robot.id} connected", "robot_id": robot.id, "kind": Event.CONNECTION_ESTABLISHED}
            )
            # Labels from the agent only at first registration: an operator's later labels win over its flags.
            if login.labels and not robot.labels:
                robot.labels = login.labels
                events.append(
                    {
                        "message": f"Robot {robot.id} registered its labels",
                        "robot_id": robot.id,
                        "kind": "robot_labels_registered",
                        "data": {"labels": robot.labels},
                    }
                )
            frames.append((robot.id, connection_frame(Event.CONNECTION_ESTABLISHED, robot.id)))
        _update_connected(changed, now)
        record_events(events)
        publish_all_on_commit(frames)


def _update_connected(robots: list[LoginRow], now: datetime) -> None:
    """Mark robots connected on their channels in one UPDATE (bulk_update's CASE per row is far slower)."""
    if not robots:
        return
    if connection.vendor != "postgresql":
        # The embedded SQLite has no jsonb_to_recordset; it serves one small fleet anyway.
        fields: dict[str, Any] = {"connected": True, "last_seen": now, "status": RobotStatus.RUNNING}
        models = [
            Robot(id=r.id, channel=r.channel, ros_master=r.ros_master, ros2=r.ros2, labels=r.labels, **fields)
            for r in robots
        ]
        Robot.objects.bulk_update(
            models, ["connected", "channel", "last_seen", "status", "ros_master", "ros2", "labels"]
        )
        return
    table = connection.ops.quote_name(Robot._meta.db_table)
    # The rows go in as one JSON document, so the query's text is the same for every batch and its
    # one parameter is quoted in C: for 500 robots a VALUES list of five placeholders a robot cost
    # the ORM thread 9 ms of CPU to bind, this 0.8 ms (measured). Labels go in as written (the rows
    # are locked), {} when none, which is what an unlabelled robot holds; a null graph becomes NULL.
    rows = [
        {"id": r.id, "channel": r.channel, "ros_master": r.ros_master, "ros2": r.ros2, "labels": r.labels}
        for r in robots
    ]
    with connection.cursor() as cursor:
        cursor.execute(
            f"UPDATE {table} SET connected = TRUE, last_seen = %s, status = %s, channel = v.channel,"
            f" ros_master = v.ros_master, ros2 = v.ros2, labels = v.labels"
            f" FROM jsonb_to_recordset(%s::jsonb)"
            f" AS v(id text, channel text, ros_master text, ros2 jsonb, labels jsonb)"
            f" WHERE {table}.id = v.id",
            [now, RobotStatus.RUNNING, json.dumps(rows)],
        )


@dataclass(frozen=True)
class Departure:
    """A robot's connection on a consumer channel that closed, and why."""

    robot_id: str
    channel: str
    reason: str


def mark_disconnected(robot_id: str, channel: str, reason: str) -> bool:
    """Record that a robot's connection closed, unless a newer connection replaced it."""
    return disconnect_robots([Departure(robot_id, channel, reason)])[0]


def disconnect_robots(departures: list[Departure]) -> list[bool]:
    """Record that robots' connections closed, unless newer ones replaced them; return which were recorded.

    In a few round trips for them all, like connect_robots: a thousand robots leaving together
    would otherwise queue a transaction each on the one ORM thread, past daphne's close timeout.
    The robots of one batch must be distinct.
    """
    held = Q()
    for departure in departures:
        held |= Q(id=departure.robot_id, channel=departure.channel)
    with transaction.atomic():
        # Locked in id order, like a batch of logins, so the two never deadlock.
        left = set(Robot.objects.select_for_update().filter(held).order_by("id").values_list("id", flat=True))
        if not left:
            return [False] * len(departures)
        Robot.objects.filter(id__in=left).update(connected=False, channel="", last_seen=timezone.now())
        _record_connections_lost([(d.robot_id, d.reason) for d in departures if d.robot_id in left])
    return [departure.robot_id in left for departure in departures]


def _record_connections_lost(lost: list[tuple[str, str]]) -> None:
    """Log that robots went offline, and why, in one INSERT; tell clients once it commits."""
    record_events(
        [
            {
                "message": f"Robot {robot_id} disconnected: {reason}",
                "robot_id": robot_id,
                "level": Level.WARNING,
                "kind": Event.CONNECTION_LOST,
                "data": {"reason": reason},
            }
            for robot_id, reason in lost
        ]
    )
    publish_all_on_commit(
        [(robot_id, connection_frame(Event.CONNECTION_LOST, robot_id, reason)) for robot_id, reason in lost]
    )


def expire_connections(processes: list[str], reason: str) -> list[str]:
    """Mark disconnected the robots held by consumers of dead server processes; return their ids.

    In one UPDATE and one INSERT of events: a dead process may have held thousands of robots, and
    this runs on the ORM thread that the robots reconnecting to this process wait for.
    """
    held_there = Q()
    for process in processes:
        held_there |= Q(channel__startswith=process + "!")
    with transaction.atomic():
        # Locked, so a robot that reconnects elsewhere meanwhile keeps its new connection.
        orphans = Robot.objects.select_for_update().filter(held_there, connected=True).order_by("id")
        robot_ids = list(orphans.values_list("id", flat=True))
        if not robot_ids:
            return []
        Robot.objects.filter(id__in=robot_ids).update(connected=False, channel="", last_seen=timezone.now())
        _record_connections_lost([(robot_id, reason) for robot_id in robot_ids])
    return robot_ids


def current_channels(channels: list[str]) -> set[str]:
    """Return which of these consumer channels still hold their robot's connection."""
    return set(Robot.objects.filter(channel__in=channels, connected=True).values_list("channel", flat=True))


def connection_frame(event: Event, robot_id: str, reason: str | None = None) -> dict[str, Any]:
    """Build the frame that tells clients a robot connected or dropped."""
    data = {"robot": robot_id} if reason is None else {"robot": robot_id, "reason": reason[:500]}
    return client_frame(event, data)


def push_to_robot(robot_id: str, event: Event, data: dict[str, Any]) -> bool:
    """Send a frame to a connected robot, resent until it acks; return False if it is offline."""
    return push_to_robots([(robot_id, event, data)]) == 1


def push_to_robots(orders: list[tuple[str, Event, dict[str, Any]]]) -> int:
    """Send frames to many connected robots at once (their channels read in one query); return how many went."""
    wanted = {robot_id for robot_id, _, _ in orders}
    channels = dict(Robot.objects.filter(id__in=wanted, connected=True).values_list("id", "channel"))
    now = time.time()
    messages = [
        (channels[robot_id], {"type": "robot.push", "frame": protocol.encode(protocol.make(event, data, now=now))})
        for robot_id, event, data in orders
        if channels.get(robot_id)
    ]

    async def send_all() -> None:
        layer = get_channel_layer()
        for channel, message in messages:
            await layer.send(channel, message)

    if messages:
        layer_sync(send_all)()
    return len(messages)


def report_shutdown(robot_id: str, reason: str | None) -> None:
    """Record that a robot announced its permanent shutdown."""
    with transaction.atomic():
        Robot.objects.filter(id=robot_id).update(status=RobotStatus.SHUTDOWN)
        record_event(f"Robot {robot_id} shut down", robot_id=robot_id, kind=Event.SHUTDOWN, data={"reason": reason})


def report_offloading(robot_id: str, mode: str) -> None:
    """Record the offloading mode a robot reports using."""
    with transaction.atomic():
        robot = Robot.objects.select_for_update().get(id=robot_id)
        if robot.config.get("offloading") != mode:
            robot.config = {**robot.config, "offloading": mode}
            robot.save(update_fields=["config"])
        publish_on_commit(robot_id, client_frame(Event.OFFLOADING, {"robot": robot_id, "mode": mode}))


def update_robot_config(robot_id: str, changes: dict[str, Any]) -> dict[str, Any]:
    """Apply a partial config change, validated as a whole, and return the new config."""
    with transaction.atomic():
        robot = Robot.objects.select_for_update().get(id=robot_id)
        robot.config = merge_config_changes(robot.config, changes)
        robot.save(update_fields=["config"])
        record_event(
            f"Config of robot {robot_id} updated", robot_id=robot_id, kind=Event.ROBOT_CONFIG_UPDATE, data=changes
        )
    return robot.config


def client_frame(event: Event, data: dict[str, Any]) -> dict[str, Any]:
    """Build a frame for clients as a JSON-ready dict."""
    return protocol.as_json_data(protocol.make(event, data, now=time.time()))


def issue_api_token(
    user: AbstractBaseUser,
    *,
    name: str = "",
    organization: Organization | None = None,
    role: str = "",
    expires_at: datetime | Literal["default"] | None = "default",
) -> tuple[str, ApiToken]:
    """Create an API token for a user and return its key (shown only now) and the token.

    A login's token (no organization) lasts API_TOKEN_TTL_S and acts with the user's roles; a
    scoped one is held to one organization and a role, until ``expires_at`` (None: until revoked).
    """
    key = API_TOKEN_PREFIX + secrets.token_urlsafe(32)
    if expires_at == "default":
        expires_at = timezone.now() + timedelta(seconds=settings.BRIDGEOS["API_TOKEN_TTL_S"])
    token = ApiToken.objects.create(
        user=user, key_hash=hash_token(key), expires_at=expires_at, name=name, organization=organization, role=role
    )
    return key, token


def issue_bridge_ticket(user: AbstractBaseUser, robot: Robot) -> tuple[str, datetime]:
    """Give a user a single-use ticket to one of their robot's bridges; return it (shown now only) and its expiry."""
    key = BRIDGE_TICKET_PREFIX + secrets.token_urlsafe(32)
    now = timezone.now()
    expires_at = now + timedelta(seconds=settings.BRIDGEOS["BRIDGE_TICKET_TTL_S"])
    with transaction.atomic():
        # Tickets are issued one click at a time: sweeping the expired ones here keeps the table tiny.
        BridgeTicket.objects.filter(expires_at__lte=now).delete()
        BridgeTicket.objects.create(key_hash=hash_token(key), user=user, robot=robot, expires_at=expires_at)
    return key, expires_at


def renew_api_token(token: ApiToken) -> ApiToken:
    """Extend a login token's validity by its full lifetime from now (a scoped token keeps its own expiry)."""
    if token.organization_id is not None:
        return token
    token.expires_at = timezone.now() + timedelta(seconds=settings.BRIDGEOS["API_TOKEN_TTL_S"])
    token.save(update_fields=["expires_at"])
    return token


def robot_config(robot_id: str) -> dict[str, Any]:
    """Return a robot's stored config."""
    return Robot.objects.values_list("config", flat=True).get(id=robot_id)


def update_robot(
    robot: Robot,
    *,
    name: str | None = None,
    config: dict[str, Any] | None = None,
    labels: dict[str, str] | None = None,
) -> Robot:
    """Rename a robot, replace its config (validated as a whole) or replace all its labels."""
    if name is not None:
        robot.name = name
    if config is not None:
        robot.config = config
    if labels is not None:
        robot.labels = labels
    with transaction.atomic():
        # save() validates the config and the labels before writing: a bad one changes nothing.
        robot.save(update_fields=["name", "config", "labels"])
        data = {"labels": robot.labels} if labels is not None else None
        record_event(f"Robot {robot.id} updated", robot_id=robot.id, kind="robot_updated", data=data)
    return robot


def hold_robot(robot_id: str) -> bool:
    """Keep the robot from being deleted until this transaction ends; False if it is gone already.

    A worker's task writing an event for a robot must take this before its other rows: the deletion
    locks the robot's row first too (``delete_robot``), so the two never wait on each other in a
    cycle, and an event never reaches commit naming a robot deleted meanwhile (a foreign key error).
    """
    if connection.vendor != "postgresql":  # SQLite (make run) writes one transaction at a time
        return Robot.objects.filter(pk=robot_id).exists()
    # FOR KEY SHARE, the lock the key's own check takes: a deletion waits on it, presence updates do not.
    with connection.cursor() as cursor:
        cursor.execute(f"SELECT 1 FROM {Robot._meta.db_table} WHERE id = %s FOR KEY SHARE", [robot_id])
        return cursor.fetchone() is not None


def delete_robot(robot: Robot) -> None:
    """Delete a robot with its skills, components, metrics and events."""
    robot_id = robot.id
    with transaction.atomic():
        channel = Robot.objects.select_for_update().values_list("channel", flat=True).get(id=robot_id)
        revoke_on_commit(channel)
        organization_id = robot.organization_id
        robot.delete()
        # Pushed live to its organization and staff: open dashboards drop the robot at once.
        record_event(
            f"Robot {robot_id} deleted",
            kind="robot_deleted",
            data={"robot": robot_id},
            organization_id=organization_id,
        )


def write_robot_families(lines: list[str]) -> None:
    """Add robots connected and last seen to a /metrics scrape (read from PostgreSQL)."""
    robots = list(Robot.objects.values_list("id", "connected", "last_seen"))
    prometheus.family(lines, "bridgeos_robots_connected", "Robots whose agent is connected.")
    lines.append(f"bridgeos_robots_connected {float(sum(connected for _, connected, _ in robots))!r}")
    prometheus.family(lines, "bridgeos_robot_connected", "1 while the robot's agent is connected.")
    lines.extend(
        f'bridgeos_robot_connected{{robot="{prometheus.label(robot_id)}"}} {1.0 if connected else 0.0}'
        for robot_id, connected, _ in robots
    )
    prometheus.family(
        lines, "bridgeos_robot_last_seen_timestamp_seconds", "When the robot was last connected (Unix time)."
    )
    lines.extend(
        f'bridgeos_robot_last_seen_timestamp_seconds{{robot="{prometheus.label(robot_id)}"}} {seen.timestamp()!r}'
        for robot_id, _, seen in robots
        if seen is not None
    )
