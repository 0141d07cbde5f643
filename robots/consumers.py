"""The door Robot Controllers connect to: /ws/robot/."""

from __future__ import annotations

import asyncio
import json
import logging
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from typing import Any

from autobahn.exception import Disconnected
from channels.db import database_sync_to_async
from channels.generic.websocket import AsyncWebsocketConsumer
from django.conf import settings
from django.core.exceptions import ValidationError

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Dedup, Direction, Envelope, Event, ProtocolError, Reliable
from bridgeos_cloud.errors import NotFound
from bridgeos_cloud.ratelimit import TokenBucket
from monitoring.ingest import get_writer
from monitoring.live import get_live_feed
from monitoring.services import record_event
from skills import services as skills

from . import services
from .dedup import applied_ids

log = logging.getLogger(__name__)

AUTH_TIMEOUT = 10.0
REQUEST_TTL = 120.0
MAX_OPEN_REQUESTS = 1000
# Closed after this many frames refused by the rate limit with no quiet second between: abuse.
MAX_FLOOD_STRIKES = 500
FLOOD_QUIET_S = 1.0


def _peek_id(raw: str | bytes | None) -> str | None:
    """Return the id of a frame that failed validation, to answer it; only on the error path."""
    try:
        frame = json.loads(raw) if raw else None
    except (ValueError, TypeError, RecursionError):
        return None
    frame_id = frame.get("id") if isinstance(frame, dict) else None
    return frame_id if protocol.is_valid_id(frame_id) else None


def _validation_message(exc: ValidationError) -> tuple[str, str | None]:
    """Flatten a Django field error into one message and the field it names."""
    for field, messages in getattr(exc, "message_dict", {"": exc.messages}).items():
        return "; ".join(messages), f"data.{field}" if field else None
    return "invalid data", None


class RobotConsumer(AsyncWebsocketConsumer):
    """One robot's connection: authenticate, apply its reports, relay commands to it."""

    handlers: dict[str, Callable[[RobotConsumer, Envelope, Any], Awaitable[bool]]] = {}

    async def connect(self) -> None:
        self.robot_id: str | None = None
        self.closing = False
        self.dedup = Dedup()
        self.reliable = Reliable()
        self.requests: OrderedDict[str, tuple[str, float]] = OrderedDict()
        options = settings.BRIDGEOS
        self.bucket = TokenBucket(options["ROBOT_FRAMES_PER_S"], options["ROBOT_FRAME_BURST"], time.monotonic())
        self.flood_strikes = 0
        self.last_refused = 0.0
        self.tasks: set[asyncio.Task] = set()
        self.retransmit_timer: asyncio.TimerHandle | None = None
        await self.accept()
        self.auth_timer = asyncio.get_running_loop().call_later(
            AUTH_TIMEOUT, self._spawn_cb, self.refuse, "authentication timed out"
        )

    # ---------------------------------------------------------------- framing

    async def send_envelope(self, envelope: Envelope) -> None:
        """Send one frame to the robot."""
        if not self.closing:
            try:
                await self.send(text_data=protocol.encode(envelope))
            except Disconnected:
                # The peer went away between our check and the write; disconnect() follows.
                self.closing = True

    async def send_reliably(self, envelope: Envelope) -> None:
        """Send a frame and resend it with backoff until the robot acknowledges it."""
        if envelope.event in protocol.REQUIRES_ACK:
            self.reliable.send(envelope, time.monotonic())
            self._schedule_retransmit()
        await self.send_envelope(envelope)

    async def reply(self, request: Envelope, event: Event, data: dict[str, Any]) -> None:
        """Answer a request of the robot."""
        await self.send_reliably(protocol.make(event, data, reply_to=request.id, now=time.time()))

    async def fail(self, message: str, *, reply_to: str | None, field: str | None = None, code: str) -> None:
        """Tell the robot a frame was refused, and why."""
        payload = {"message": message[:2000], "code": code}
        if field:
            payload["field"] = field
        await self.send_envelope(protocol.make(Event.ERROR_MESSAGE, payload, reply_to=reply_to, now=time.time()))

    async def ack(self, envelope: Envelope) -> None:
        await self.send_envelope(protocol.ack_frame(envelope.id, now=time.time()))

    def _spawn(self, coroutine: Awaitable[Any]) -> None:
        task = asyncio.ensure_future(coroutine)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    def _spawn_cb(self, function: Callable[..., Awaitable[Any]], *args: Any) -> None:
        self._spawn(function(*args))

    # ---------------------------------------------------------------- receiving

    async def receive(self, text_data: str | None = None, bytes_data: bytes | None = None) -> None:
        raw = text_data if text_data is not None else bytes_data
        if self.closing:
            return
        if self.robot_id is None:
            await self.authenticate(raw)
            return
        now = time.monotonic()
        if not self.bucket.allow(now):
            await self.flooded(raw, now)
            return
        try:
            envelope = protocol.decode(raw, direction=Direction.ROBOT_TO_CLOUD)
        except ProtocolError as exc:
            await self.fail(exc.message, reply_to=_peek_id(raw), field=exc.field, code=exc.code)
            return
        await self.dispatch_envelope(envelope)

    async def flooded(self, raw: str | bytes | None, now: float) -> None:
        """Refuse a frame over the rate limit; close the connection if the flood goes on."""
        if now - self.last_refused > FLOOD_QUIET_S:
            self.flood_strikes = 0
        self.last_refused = now
        self.flood_strikes += 1
        if self.flood_strikes >= MAX_FLOOD_STRIKES:
            await self.fail("too many frames, closing", reply_to=None, code="rate_limited")
            await self.close_with(4008, "flooding")
            return
        # Not acked, so the robot keeps the frame and sends it again later: nothing is lost.
        await self.fail("rate limit exceeded, send again later", reply_to=_peek_id(raw), code="rate_limited")

    async def dispatch_envelope(self, envelope: Envelope) -> None:
        """Route one valid frame from the robot to its handler."""
        event = envelope.event
        if envelope.reply_to is not None and envelope.reply_to in self.requests:
            await self.forward_reply(envelope)
        if event == Event.ACK:
            self.reliable.on_ack(envelope.reply_to)
            return
        payload = protocol.parse_payload(envelope)
        named = getattr(payload, "robot", None)
        if named is not None and named != self.robot_id:
            await self.fail(
                "a robot may only speak for itself", reply_to=envelope.id, field="data.robot", code="forbidden"
            )
            return
        needs_ack = event in protocol.REQUIRES_ACK
        if needs_ack and self.dedup.seen(envelope.id):
            await self.ack(envelope)
            return
        try:
            ack_now = await self.handlers[event](self, envelope, payload)
        except NotFound as exc:
            self.dedup.forget(envelope.id)
            await self.fail(exc.message, reply_to=envelope.id, field=exc.field, code="not_found")
            return
        except ValidationError as exc:
            self.dedup.forget(envelope.id)
            message, field = _validation_message(exc)
            await self.fail(message, reply_to=envelope.id, field=field, code="invalid_payload")
            return
        except Exception:
            self.dedup.forget(envelope.id)
            log.exception("robot %s: handling %s failed", self.robot_id, event)
            await self.fail("internal error, send again later", reply_to=envelope.id, code="internal_error")
            return
        if needs_ack and ack_now:
            applied_ids().add(self.robot_id, envelope.id)
            await self.ack(envelope)

    # ---------------------------------------------------------------- authentication

    async def authenticate(self, raw: str | bytes | None) -> None:
        """Accept the first frame only if it is a valid authentication_robot."""
        self.auth_timer.cancel()
        try:
            envelope = protocol.decode(raw, direction=Direction.ROBOT_TO_CLOUD)
        except ProtocolError as exc:
            await self.refuse(f"first frame must be authentication_robot ({exc})", reply_to=_peek_id(raw))
            return
        if envelope.event != Event.AUTHENTICATION_ROBOT:
            await self.refuse("first frame must be authentication_robot", reply_to=envelope.id)
            return
        credentials = protocol.parse_payload(envelope)
        robot = await database_sync_to_async(services.authenticate_robot)(credentials.robot, credentials.token)
        if robot is None:
            await self.refuse("unknown robot or wrong token", reply_to=envelope.id)
            return
        self.robot_id = robot.id
        self.dedup.load(await applied_ids().load(robot.id))
        connected = await database_sync_to_async(services.mark_connected)(robot.id, self.channel_name)
        if connected["replaced_channel"]:
            await self.channel_layer.send(connected["replaced_channel"], {"type": "robot.replaced"})
        await self.send_envelope(
            protocol.make(Event.AUTHENTICATION_SUCCESS, {"robot": robot.id}, reply_to=envelope.id, now=time.time())
        )
        await self.send_reliably(protocol.make(Event.CONNECTION_ESTABLISHED, {"robot": robot.id}, now=time.time()))
        await self.send_reliably(protocol.make(Event.ROBOT_CONFIG, {"config": connected["config"]}, now=time.time()))

    async def refuse(self, reason: str, reply_to: str | None = None) -> None:
        """Answer authentication_failure and close."""
        if self.closing:
            return
        frame = protocol.make(
            Event.AUTHENTICATION_FAILURE, {"reason": reason[:500]}, reply_to=reply_to, now=time.time()
        )
        await self.send_envelope(frame)
        await self.close_with(4001, "authentication failed")

    async def close_with(self, code: int, reason: str) -> None:
        if not self.closing:
            self.closing = True
            self.close_reason = reason
            await self.close(code)

    # ---------------------------------------------------------------- commands from the cloud

    async def robot_command(self, message: dict[str, Any]) -> None:
        """Send a command relayed by relay_command, remembering who waits for the reply."""
        envelope = protocol.decode(message["frame"])
        now = time.monotonic()
        self.requests[envelope.id] = (message["reply_channel"], now)
        while self.requests and (
            len(self.requests) > MAX_OPEN_REQUESTS or next(iter(self.requests.values()))[1] < now - REQUEST_TTL
        ):
            self.requests.popitem(last=False)
        await self.send_reliably(envelope)

    async def forward_reply(self, envelope: Envelope) -> None:
        """Hand the robot's answer to whoever relayed the command."""
        reply_channel, _ = self.requests.pop(envelope.reply_to)
        await self.channel_layer.send(reply_channel, {"type": "robot.reply", "frame": protocol.encode(envelope)})

    async def robot_replaced(self, message: dict[str, Any]) -> None:
        """Close this connection: the robot reconnected on a newer one."""
        await self.close_with(4009, "replaced by a newer connection")

    def _schedule_retransmit(self) -> None:
        if self.retransmit_timer is not None:
            self.retransmit_timer.cancel()
        due = self.reliable.next_due()
        if due is not None:
            delay = max(0.0, due - time.monotonic())
            self.retransmit_timer = asyncio.get_running_loop().call_later(delay, self._spawn_cb, self.retransmit)

    async def retransmit(self) -> None:
        """Resend every unacknowledged frame whose time has come."""
        self.retransmit_timer = None
        if self.closing:
            return
        for envelope in self.reliable.due(time.monotonic()):
            await self.send_envelope(envelope)
        self._schedule_retransmit()

    # ---------------------------------------------------------------- closing

    async def disconnect(self, code: int) -> None:
        self.closing = True
        self.auth_timer.cancel()
        if self.retransmit_timer is not None:
            self.retransmit_timer.cancel()
        for task in self.tasks:
            task.cancel()
        for reply_channel, _ in self.requests.values():
            await self.channel_layer.send(reply_channel, {"type": "robot.reply", "offline": True})
        self.requests.clear()
        if self.robot_id is not None:
            reason = getattr(self, "close_reason", None) or f"connection closed (code {code})"
            await applied_ids().flush()
            await database_sync_to_async(services.mark_disconnected)(self.robot_id, self.channel_name, reason)


def handles(*events: Event) -> Callable:
    """Register a RobotConsumer method as the handler of events."""

    def register(function: Callable) -> Callable:
        for event in events:
            RobotConsumer.handlers[event] = function
        return function

    return register


def sync(function: Callable[..., Any]) -> Callable[..., Awaitable[Any]]:
    return database_sync_to_async(function)


# Each handler applies one event and returns whether to ack it now (metrics ack after commit).


@handles(Event.METRICS)
async def on_metrics(consumer: RobotConsumer, envelope: Envelope, payload: Any) -> bool:
    points = payload.metrics
    if not points:
        return True
    robot_id = consumer.robot_id
    get_live_feed().add_metrics(robot_id, points)
    written = get_writer().add(robot_id, points)

    def acknowledge(future: asyncio.Future) -> None:
        if future.cancelled() or future.exception() is not None:
            consumer.dedup.forget(envelope.id)
            consumer._spawn(
                consumer.fail("metrics not stored, send again later", reply_to=envelope.id, code="unavailable")
            )
        else:
            applied_ids().add(robot_id, envelope.id)
            consumer._spawn(consumer.ack(envelope))

    written.add_done_callback(acknowledge)
    return False


@handles(Event.SKILL_STATUS)
async def on_skill_status(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(skills.report_skill_status)(consumer.robot_id, p.skill, p.status, p.message)
    return True


@handles(Event.COMPONENT_STATUS)
async def on_component_status(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(skills.report_component_status)(consumer.robot_id, p.skill, p.component, p.status, p.location, p.message)
    return True


@handles(Event.COMPONENT_LOCATION)
async def on_component_location(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(skills.report_component_location)(consumer.robot_id, p.skill, p.component, p.location)
    return True


@handles(Event.COMPONENT_INFORMATION)
async def on_component_information(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    container = p.container.model_dump(mode="json", exclude_none=True)
    await sync(skills.report_component_information)(consumer.robot_id, p.skill, p.component, p.location, container)
    return True


@handles(Event.SKILL_CONNECT)
async def on_skill_connect(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(skills.report_skill_connect)(consumer.robot_id, p.skill, p.manager_url)
    return True


@handles(Event.SKILL_CONFIG)
async def on_skill_config(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(skills.report_skill_config)(consumer.robot_id, p.skill, dict(p.config))
    return True


@handles(Event.OFFLOADING)
async def on_offloading(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(services.report_offloading)(consumer.robot_id, p.mode)
    return True


@handles(Event.SHUTDOWN)
async def on_shutdown(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(services.report_shutdown)(consumer.robot_id, p.reason)
    return True


@handles(Event.ROBOT_CONFIG_GET)
async def on_robot_config_get(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    config = await sync(services.robot_config)(consumer.robot_id)
    await consumer.reply(envelope, Event.ROBOT_CONFIG, {"config": config})
    return False


@handles(Event.SKILL_CONFIG_GET)
async def on_skill_config_get(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    skill = await sync(skills.skill_state)(consumer.robot_id, p.skill)
    await consumer.reply(envelope, Event.SKILL_CONFIG, {"skill": skill.skill_id, "config": skill.config})
    return False


@handles(Event.COMPONENT_STATUS_GET)
async def on_component_status_get(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    component = await sync(skills.component_state)(consumer.robot_id, p.skill, p.component)
    data = {"skill": p.skill, "component": p.component, "status": component.status}
    if component.active_location:
        data["location"] = component.active_location
    await consumer.reply(envelope, Event.COMPONENT_STATUS, data)
    return False


@handles(Event.ERROR_MESSAGE)
async def on_error_message(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(record_event)(
        f"Robot reported: {p.message}",
        robot_id=consumer.robot_id,
        level="error",
        source="robot",
        kind=Event.ERROR_MESSAGE,
        data={"field": p.field, "code": p.code, "reply_to": envelope.reply_to},
    )
    return False


@handles(Event.AUTHENTICATION_ROBOT)
async def on_authentication_again(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await consumer.fail("already authenticated", reply_to=envelope.id, code="invalid_state")
    return False


@handles(Event.COMPONENT_START, Event.COMPONENT_STOP)
async def on_cloud_component_request(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    # The robot asks the cloud to run (or stop) the cloud side of a component.
    await sync(skills.component_state)(consumer.robot_id, p.skill, p.component)
    await consumer.fail(
        "this cloud does not orchestrate cloud components yet; run the component on the robot",
        reply_to=envelope.id,
        code="unsupported",
    )
    return False
