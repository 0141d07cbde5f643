"""The door dashboards and apps connect to: /ws/client/, a live feed plus commands."""

from __future__ import annotations

import asyncio
import json
import logging
import time
from typing import Any

from channels.db import database_sync_to_async
from django.conf import settings
from django.core.exceptions import ValidationError

from audit import services as audit
from bridgeos_agent import protocol
from bridgeos_agent.protocol import Dedup, Direction, Envelope, Event
from bridgeos_cloud.consumers import CLOSE_AUTH_FAILED, ProtocolConsumer, validation_message
from bridgeos_cloud.errors import NotFound
from logs.tail import LogTail
from monitoring import prometheus
from monitoring.live import LIVE_GROUP
from robots import access
from robots import services as robots
from teams.roles import Right

from . import services

log = logging.getLogger(__name__)

MAX_COMMANDS_IN_FLIGHT = 16
# A robot the user does not know yet triggers at most one reload of their robots per this interval.
VISIBLE_REFRESH_S = 1.0
RELAYED = frozenset(
    {
        Event.ROBOT_START,
        Event.ROBOT_STOP,
        Event.SHUTDOWN,
        Event.SKILL_START,
        Event.SKILL_STOP,
        Event.COMPONENT_START,
        Event.COMPONENT_STOP,
        Event.COMPONENT_MIGRATE,
    }
)
# Config changes are stored first, so an offline robot receives them when it reconnects.
STORED_THEN_RELAYED = frozenset({Event.ROBOT_CONFIG_UPDATE, Event.OFFLOADING})
IGNORED = frozenset({Event.ACK, Event.ERROR_MESSAGE})
# Live tails of component logs: served by the connection's LogTail (a read, as every other).
LOG_TAILS = frozenset({Event.LOGS_SUBSCRIBE, Event.LOGS_UNSUBSCRIBE})
NEEDED = {Right.READ: "viewer", Right.COMMAND: "operator", Right.ADMINISTER: "admin"}


def right_for(event: Event) -> Right:
    """Return the right a client's request needs: settings are an admin's, commands an operator's, reads a viewer's."""
    if event == Event.ROBOT_CONFIG_UPDATE:
        return Right.ADMINISTER
    return Right.COMMAND if event in RELAYED or event in STORED_THEN_RELAYED else Right.READ


class ClientConsumer(ProtocolConsumer):
    """One dashboard or app: authenticate, stream its robots live, carry its commands."""

    direction = Direction.CLIENT_TO_CLOUD
    auth_event = Event.AUTHENTICATION_CLIENT

    @property
    def rate_setting(self) -> tuple[float, float]:
        return settings.BRIDGEOS["CLIENT_FRAMES_PER_S"], settings.BRIDGEOS["CLIENT_FRAME_BURST"]

    async def connect(self) -> None:
        self.user = None
        self.actor: access.Actor | None = None
        self.visible: set[str] | None = set()
        self.visible_loaded_at = 0.0
        # The robots whose live metrics this client asked for (metrics_subscribe); None: every robot it may see.
        self.subscribed: set[str] | None = None
        # Subscriptions received so far: they are checked side by side, and the last one sent must win.
        self.subscriptions = 0
        self.dedup = Dedup(capacity=1000)
        self.log_tail = LogTail(self)
        await super().connect()

    async def authenticate(self, envelope: Envelope) -> bool:
        """Accept an API token, or with none the session of a logged-in dashboard (in the organization it picked)."""
        actor = await database_sync_to_async(self.actor_for)(protocol.parse_payload(envelope).token)
        if actor is None:
            await self.refuse("invalid token or no logged-in session", reply_to=envelope.id)
            return False
        self.actor, self.user = actor, actor.user
        user = actor.user
        await self.refresh_visible(force=True)
        if actor.token is not None:
            # Revoking the token (or its user's membership) closes this connection at once.
            await self.channel_layer.group_add(access.token_group(actor.token.pk), self.channel_name)
        # A change of the user's memberships or account reloads the roles loaded above.
        await self.channel_layer.group_add(access.user_group(user.pk), self.channel_name)
        await self.channel_layer.group_add(LIVE_GROUP, self.channel_name)
        prometheus.LIVE_CLIENTS.inc()
        await self.answer(envelope, Event.AUTHENTICATION_SUCCESS, {"user": user.get_username()[:150]})
        return True

    def actor_for(self, token: str | None) -> access.Actor | None:
        """Return who this connection acts for, with their roles loaded; None when refused."""
        if token is not None:
            found = access.api_token(token)
            actor = None if found is None else access.token_actor(found)
        else:
            user = self.scope.get("user")
            if user is None or not user.is_authenticated:
                return None
            session = self.scope.get("session")
            actor = access.Actor(user, organization_id=session.get(access.SESSION_ORGANIZATION) if session else None)
        if actor is not None:
            actor.roles()
        return actor

    async def token_revoked(self, message: dict[str, Any]) -> None:
        """Close the connection of a token that was revoked, expired by its membership's end, or deleted."""
        await self.close_with(CLOSE_AUTH_FAILED, "token revoked")

    async def membership_changed(self, message: dict[str, Any]) -> None:
        """Reload the roles and robots after the user's memberships or account changed; close if they may not act."""
        actor = await database_sync_to_async(access.current_actor)(self.actor)
        if actor is None:
            await self.close_with(CLOSE_AUTH_FAILED, "no longer a member")
            return
        self.actor, self.user = actor, actor.user
        await self.refresh_visible(force=True)

    async def handle_frame(self, envelope: Envelope) -> None:
        if envelope.event in IGNORED:
            return
        # Over one socket nothing is lost, so a resent command is a retransmission: run it once.
        if envelope.event in protocol.REQUIRES_ACK and self.dedup.seen(envelope.id):
            return
        if len(self.tasks) >= MAX_COMMANDS_IN_FLIGHT:
            await self.fail("too many requests in flight", reply_to=envelope.id, code="rate_limited")
            return
        self.spawn(self.handle(envelope))

    async def closed(self, code: int) -> None:
        await self.log_tail.close()
        if self.user is not None:
            prometheus.LIVE_CLIENTS.dec()
            await self.channel_layer.group_discard(LIVE_GROUP, self.channel_name)
            await self.channel_layer.group_discard(access.user_group(self.user.pk), self.channel_name)

    # ---------------------------------------------------------------- who may see what

    async def refresh_visible(self, *, force: bool = False) -> None:
        """Reload the robots this user may see, at most every few seconds."""
        now = time.monotonic()
        if force or now - self.visible_loaded_at > VISIBLE_REFRESH_S:
            self.visible_loaded_at = now
            # The actor, not the user: a scoped token or a session's pick sees its one organization's robots.
            self.visible = await database_sync_to_async(access.visible_robot_ids)(self.actor)

    async def sees(self, robot_id: str, *, recheck: bool = False) -> bool:
        """Tell whether the user may see a robot, catching robots added since connecting."""
        if self.visible is None or robot_id in self.visible:
            return True
        await self.refresh_visible(force=recheck)
        return self.visible is None or robot_id in self.visible

    # ---------------------------------------------------------------- the live feed

    async def live_metrics(self, message: dict[str, Any]) -> None:
        """Send the latest metric values of the robots this user may see (and subscribed to), one frame per robot."""
        now = time.time()
        robots: dict[str, str] = message["robots"]
        if self.subscribed is not None:
            # A page of a 10,000-robot fleet: walk its hundred robots, not every robot in the message.
            robots = {robot_id: robots[robot_id] for robot_id in self.subscribed if robot_id in robots}
        for robot_id, data in robots.items():
            if await self.sees(robot_id):
                # The payload was validated on the way in and encoded once for all clients.
                await self.send_text(
                    f'{{"event":"metrics","id":"{protocol.new_id()}","reply_to":null,"data":{data},"ts":{now!r}}}'
                )

    async def live_event(self, message: dict[str, Any]) -> None:
        """Pass on a state change of a robot this user may see (of no robot: staff only)."""
        robot_id = message["robot"]
        if message.get("organization") is not None:
            # The robot is gone from the database, so its organization is named in the message.
            allowed = self.visible is None or self.actor.role_in(message["organization"]) is not None
        elif robot_id is None:
            allowed = self.visible is None
        else:
            # A robot connecting may be one added since this client connected: always recheck then.
            recheck = message["frame"].get("event") == Event.CONNECTION_ESTABLISHED
            allowed = await self.sees(robot_id, recheck=recheck)
        if allowed:
            await self.send_text(json.dumps(message["frame"], separators=(",", ":")))

    async def logs_lines(self, message: dict[str, Any]) -> None:
        """Pass on new log lines of the components this client tails."""
        await self.log_tail.push(message)

    async def live_events(self, message: dict[str, Any]) -> None:
        """Pass on many state changes published together (a connect storm), each as live_event would."""
        for event in message["events"]:
            await self.live_event(event)

    # ---------------------------------------------------------------- commands

    async def handle(self, envelope: Envelope) -> None:
        """Authorise one request, then answer it from the database or relay it to the robot."""
        payload = protocol.parse_payload(envelope)
        robot_id = getattr(payload, "robot", None)
        # A metrics subscription names many robots, not one: subscribe_metrics judges them all at once.
        if robot_id is None and not isinstance(payload, protocol.MetricsSubscribe):
            await self.fail(
                "name the robot this request is for", reply_to=envelope.id, field="data.robot", code="invalid_payload"
            )
            return
        outcome = "ok"
        try:
            if isinstance(payload, protocol.MetricsSubscribe):
                await self.subscribe_metrics(envelope, payload)
                return
            allowed = await database_sync_to_async(access.may_on_robot)(self.actor, robot_id, right_for(envelope.event))
            if allowed is None:
                raise NotFound(f"no robot {robot_id!r}", field="data.robot")
            if not allowed:
                outcome = "denied"
                await self.fail(
                    f"{envelope.event} needs the {NEEDED[right_for(envelope.event)]} role in the robot's organization",
                    reply_to=envelope.id,
                    field="event",
                    code="forbidden",
                )
                return
            if envelope.event in STORED_THEN_RELAYED:
                await database_sync_to_async(services.store_config_change)(envelope.event, robot_id, payload)
                outcome = await self.relay(envelope, robot_id, stored=True)
            elif envelope.event in RELAYED:
                outcome = await self.relay(envelope, robot_id)
            elif envelope.event in LOG_TAILS:
                await self.log_tail.handle(envelope, robot_id, payload)
            else:
                event, data = await database_sync_to_async(services.answer_from_database)(
                    envelope.event, robot_id, payload
                )
                await self.answer(envelope, event, data)
        except NotFound as exc:
            outcome = "not_found"
            await self.fail(exc.message, reply_to=envelope.id, field=exc.field, code="not_found")
        except ValidationError as exc:
            outcome = "invalid"
            message, field = validation_message(exc)
            await self.fail(message, reply_to=envelope.id, field=field, code="invalid_payload")
        except Exception:
            outcome = "failed"
            log.exception("client request %s failed", envelope.event)
            await self.fail("internal error", reply_to=envelope.id, code="internal_error")
        finally:
            if envelope.event in RELAYED or envelope.event in STORED_THEN_RELAYED:
                # Shielded: a client that leaves cancels what its connection was doing, and an entry
                # still queued for the database thread was cancelled with it, the command unrecorded.
                await asyncio.shield(
                    database_sync_to_async(audit.record_client_command)(
                        self.actor, envelope.event, robot_id, outcome, self.scope.get("client")
                    )
                )

    async def subscribe_metrics(self, envelope: Envelope, payload: protocol.MetricsSubscribe) -> None:
        """Narrow the live metrics to the named robots; refuse the lot if one is not the client's to see."""
        self.subscriptions += 1
        asked = self.subscriptions
        robots = set(payload.robots)
        hidden = await database_sync_to_async(services.robots_out_of_sight)(self.actor, robots)
        if hidden:
            # The words for another organization's robot and for a missing one are the same.
            raise NotFound(f"no robot {min(hidden)!r}", field="data.robots")
        # One sent later but checked sooner must not be undone by this one.
        if asked == self.subscriptions:
            self.subscribed = robots
        await self.send_envelope(protocol.ack_frame(envelope.id, now=time.time()))

    async def relay(self, envelope: Envelope, robot_id: str, *, stored: bool = False) -> str:
        """Send a command to the robot and pass its reply back under the client's id; return the audit outcome."""
        data = {key: value for key, value in envelope.data.items() if key != "robot"}
        try:
            reply = await robots.relay_command(robot_id, envelope.event, data, wait=settings.BRIDGEOS["COMMAND_WAIT_S"])
        except robots.RobotOffline:
            if stored:
                await self.send_envelope(protocol.ack_frame(envelope.id, now=time.time()))
                return "ok"  # stored: the robot gets it when it connects
            await self.fail(
                f"robot {robot_id} is offline", reply_to=envelope.id, field="data.robot", code="robot_offline"
            )
            return "failed"
        except robots.CommandTimeout as exc:
            await self.fail(str(exc), reply_to=envelope.id, code="timeout")
            return "failed"
        data = reply.data
        if issubclass(protocol.PAYLOADS[reply.event], protocol.RobotScoped):
            # Client links are not bound to one robot, so say which robot answered.
            data = {**data, "robot": robot_id}
        answer = reply.model_copy(update={"reply_to": envelope.id, "data": data})
        await self.send_envelope(answer)
        return "failed" if reply.event == Event.ERROR_MESSAGE else "ok"
