"""The door dashboards and apps connect to: /ws/client/, a live feed plus commands."""

from __future__ import annotations

import json
import logging
import time
from typing import Any

from channels.db import database_sync_to_async
from django.conf import settings
from django.core.exceptions import ValidationError

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Dedup, Direction, Envelope, Event
from bridgeos_cloud.consumers import ProtocolConsumer, validation_message
from bridgeos_cloud.errors import NotFound
from monitoring import prometheus
from monitoring.live import LIVE_GROUP
from robots import access
from robots import services as robots

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


class ClientConsumer(ProtocolConsumer):
    """One dashboard or app: authenticate, stream its robots live, carry its commands."""

    direction = Direction.CLIENT_TO_CLOUD
    auth_event = Event.AUTHENTICATION_CLIENT

    @property
    def rate_setting(self) -> tuple[float, float]:
        return settings.BRIDGEOS["CLIENT_FRAMES_PER_S"], settings.BRIDGEOS["CLIENT_FRAME_BURST"]

    async def connect(self) -> None:
        self.user = None
        self.visible: set[str] | None = set()
        self.visible_loaded_at = 0.0
        self.dedup = Dedup(capacity=1000)
        await super().connect()

    async def authenticate(self, envelope: Envelope) -> bool:
        """Accept an API token, or with none the session of a logged-in dashboard."""
        token = protocol.parse_payload(envelope).token
        if token is not None:
            user = await database_sync_to_async(access.authenticate_api_token)(token)
        else:
            session_user = self.scope.get("user")
            user = session_user if session_user is not None and session_user.is_authenticated else None
        if user is None:
            await self.refuse("invalid token or no logged-in session", reply_to=envelope.id)
            return False
        self.user = user
        await self.refresh_visible(force=True)
        await self.channel_layer.group_add(LIVE_GROUP, self.channel_name)
        prometheus.LIVE_CLIENTS.inc()
        await self.answer(envelope, Event.AUTHENTICATION_SUCCESS, {"user": user.get_username()[:150]})
        return True

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
        if self.user is not None:
            prometheus.LIVE_CLIENTS.dec()
            await self.channel_layer.group_discard(LIVE_GROUP, self.channel_name)

    # ---------------------------------------------------------------- who may see what

    async def refresh_visible(self, *, force: bool = False) -> None:
        """Reload the robots this user may see, at most every few seconds."""
        now = time.monotonic()
        if force or now - self.visible_loaded_at > VISIBLE_REFRESH_S:
            self.visible_loaded_at = now
            self.visible = await database_sync_to_async(access.visible_robot_ids)(self.user)

    async def sees(self, robot_id: str, *, recheck: bool = False) -> bool:
        """Tell whether the user may see a robot, catching robots added since connecting."""
        if self.visible is None or robot_id in self.visible:
            return True
        await self.refresh_visible(force=recheck)
        return self.visible is None or robot_id in self.visible

    # ---------------------------------------------------------------- the live feed

    async def live_metrics(self, message: dict[str, Any]) -> None:
        """Send the latest metric values of the robots this user may see, one frame per robot."""
        now = time.time()
        for robot_id, data in message["robots"].items():
            if await self.sees(robot_id):
                # The payload was validated on the way in and encoded once for all clients.
                await self.send_text(
                    f'{{"event":"metrics","id":"{protocol.new_id()}","reply_to":null,"data":{data},"ts":{now!r}}}'
                )

    async def live_event(self, message: dict[str, Any]) -> None:
        """Pass on a state change of a robot this user may see (of no robot: staff only)."""
        robot_id = message["robot"]
        if message.get("owner") is not None:
            # The robot is gone from the database, so its owner is named in the message.
            allowed = self.visible is None or message["owner"] == self.user.pk
        elif robot_id is None:
            allowed = self.visible is None
        else:
            # A robot connecting may be one added since this client connected: always recheck then.
            recheck = message["frame"].get("event") == Event.CONNECTION_ESTABLISHED
            allowed = await self.sees(robot_id, recheck=recheck)
        if allowed:
            await self.send_text(json.dumps(message["frame"], separators=(",", ":")))

    async def live_events(self, message: dict[str, Any]) -> None:
        """Pass on many state changes published together (a connect storm), each as live_event would."""
        for event in message["events"]:
            await self.live_event(event)

    # ---------------------------------------------------------------- commands

    async def handle(self, envelope: Envelope) -> None:
        """Authorise one request, then answer it from the database or relay it to the robot."""
        payload = protocol.parse_payload(envelope)
        robot_id = getattr(payload, "robot", None)
        if robot_id is None:
            await self.fail(
                "name the robot this request is for", reply_to=envelope.id, field="data.robot", code="invalid_payload"
            )
            return
        try:
            if not await database_sync_to_async(access.can_see)(self.user, robot_id):
                raise NotFound(f"no robot {robot_id!r}", field="data.robot")
            if envelope.event in STORED_THEN_RELAYED:
                await database_sync_to_async(services.store_config_change)(envelope.event, robot_id, payload)
                await self.relay(envelope, robot_id, stored=True)
            elif envelope.event in RELAYED:
                await self.relay(envelope, robot_id)
            else:
                event, data = await database_sync_to_async(services.answer_from_database)(
                    envelope.event, robot_id, payload
                )
                await self.answer(envelope, event, data)
        except NotFound as exc:
            await self.fail(exc.message, reply_to=envelope.id, field=exc.field, code="not_found")
        except ValidationError as exc:
            message, field = validation_message(exc)
            await self.fail(message, reply_to=envelope.id, field=field, code="invalid_payload")
        except Exception:
            log.exception("client request %s failed", envelope.event)
            await self.fail("internal error", reply_to=envelope.id, code="internal_error")

    async def relay(self, envelope: Envelope, robot_id: str, *, stored: bool = False) -> None:
        """Send a command to the robot and pass its reply back under the client's id."""
        data = {key: value for key, value in envelope.data.items() if key != "robot"}
        try:
            reply = await robots.relay_command(robot_id, envelope.event, data, wait=settings.BRIDGEOS["COMMAND_WAIT_S"])
        except robots.RobotOffline:
            if stored:
                await self.send_envelope(protocol.ack_frame(envelope.id, now=time.time()))
                return
            await self.fail(
                f"robot {robot_id} is offline", reply_to=envelope.id, field="data.robot", code="robot_offline"
            )
            return
        except robots.CommandTimeout as exc:
            await self.fail(str(exc), reply_to=envelope.id, code="timeout")
            return
        data = reply.data
        if issubclass(protocol.PAYLOADS[reply.event], protocol.RobotScoped):
            # Client links are not bound to one robot, so say which robot answered.
            data = {**data, "robot": robot_id}
        answer = reply.model_copy(update={"reply_to": envelope.id, "data": data})
        await self.send_envelope(answer)
