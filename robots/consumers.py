"""The door Robot Controllers connect to: /ws/robot/."""

from __future__ import annotations

import asyncio
import logging
import time
from collections import OrderedDict
from collections.abc import Awaitable, Callable
from contextlib import nullcontext
from functools import cached_property
from typing import Any

from django.conf import settings
from django.core.exceptions import ValidationError

from bridgeos_agent import protocol
from bridgeos_agent.labels import label_problems
from bridgeos_agent.logonce import LogOnce
from bridgeos_agent.protocol import Dedup, Direction, Envelope, Event, Reliable
from bridgeos_cloud.batching import Batcher
from bridgeos_cloud.consumers import CLOSE_TOO_MANY_FAILURES, ProtocolConsumer, validation_message
from bridgeos_cloud.errors import NotFound
from bridgeos_cloud.loopowned import loop_object
from bridgeos_cloud.servertuning import gathered_writes
from monitoring import prometheus
from monitoring.ingest import get_writer
from monitoring.live import get_live_feed
from monitoring.services import record_event
from skills import services as skills
from skills.cloud.reporting import cloud_reports_for
from skills.cloud.volumes import CloudVolumes, robots_with_cloud_volumes

from . import dedup, rotation, services
from .bridges import RobotBridges
from .dbthreads import AlreadyApplied, applying, sync
from .dedup import applied_ids
from .local import deliver, register_local
from .presence import get_presence

log = logging.getLogger(__name__)

REQUEST_TTL = 120.0
VOLUME_SCAN_S = 1.0
CHUNK_WAIT_S = 30.0
MAX_OPEN_REQUESTS = 1000
# Metrics, volume changes and log lines are kept from applying twice by their own stores (log lines by their key).
OWN_DEDUP = frozenset({Event.METRICS, Event.VOLUME_CHANGES, Event.COMPONENT_LOGS})
CLOSE_REPLACED = 4009
CLOSE_REVOKED = 4004
# How the agent's encoder starts a bridge event: such frames skip the robot's report rate limit.
BRIDGE_FRAME_PREFIX = '{"event":"bridge_'

saving_failures = LogOnce(log, "saving applied frame ids in Redis before acking", traceback=True)


Reports = list[tuple[Event, dict[str, Any]]]


def connect_batch(logins: list[services.Login]) -> list[tuple[services.Connected, Reports, bool]]:
    """Authenticate and connect robots together: each outcome, its cloud copies' reports, whether it has volumes."""
    outcomes = services.connect_robots(logins)
    robots = [outcome.robot for outcome in outcomes if outcome.robot]
    reports = cloud_reports_for(robots)
    with_volumes = robots_with_cloud_volumes(robots)
    return [(outcome, reports.get(outcome.robot or "", []), outcome.robot in with_volumes) for outcome in outcomes]


def login_queue() -> Batcher[services.Login, tuple[services.Connected, Reports, bool]]:
    """Return this event loop's queue of robot logins, batched so a connect storm shares its round trips."""
    return loop_object(
        "robot logins",
        lambda: Batcher(connect_batch, key=lambda login: login.robot_id),
        usable=lambda batcher: not batcher.closed,
    )


def goodbye_queue() -> Batcher[services.Departure, bool]:
    """Return this event loop's queue of closed robot connections, recorded in batches like logins."""
    return loop_object(
        "robot goodbyes",
        lambda: Batcher(services.disconnect_robots, key=lambda departure: departure.robot_id),
        usable=lambda batcher: not batcher.closed,
    )


class RobotConsumer(ProtocolConsumer):
    """One robot's connection: authenticate, apply its reports, relay commands to it."""

    direction = Direction.ROBOT_TO_CLOUD
    auth_event = Event.AUTHENTICATION_ROBOT
    handlers: dict[str, Callable[[RobotConsumer, Envelope, Any], Awaitable[bool]]] = {}

    @property
    def rate_setting(self) -> tuple[float, float]:
        return settings.BRIDGEOS["ROBOT_FRAMES_PER_S"], settings.BRIDGEOS["ROBOT_FRAME_BURST"]

    async def connect(self) -> None:
        self.robot_id: str | None = None
        self.dedup = Dedup(capacity=dedup.WINDOW)
        self.reliable = Reliable()
        self.requests: OrderedDict[str, tuple[str, float]] = OrderedDict()
        self.rekeys: set[str] = set()  # ids of robot_rekey frames the robot has not acked yet
        self.retransmit_timer: asyncio.TimerHandle | None = None
        self.volume_scanner: asyncio.Future | None = None
        # Set once the login is answered (or refused, or the socket closed): a command delivered from this
        # process meanwhile runs in its sender's task, and went out ahead of authentication_success,
        # which the agent then took for a refusal and stopped.
        self.login_answered = asyncio.Event()
        self.chunk_requests: dict[str, asyncio.Future[Envelope]] = {}
        self.volume_writes: dict[str, set[asyncio.Future]] = {}  # per Skill: volume changes, and what waits on them
        self.bridges = RobotBridges("")
        register_local(self)
        await super().connect()

    async def send_reliably(self, envelope: Envelope) -> None:
        """Send a frame and resend it with backoff until the robot acknowledges it."""
        if envelope.event in protocol.REQUIRES_ACK:
            self.reliable.send(envelope, time.monotonic())
            self._schedule_retransmit()
        await self.send_envelope(envelope)

    async def reply(self, request: Envelope, event: Event, data: dict[str, Any]) -> None:
        """Answer a request of the robot, resending until acknowledged."""
        await self.send_reliably(protocol.make(event, data, reply_to=request.id, now=time.time()))

    async def handle_frame(self, envelope: Envelope) -> None:
        await self.dispatch_envelope(envelope)

    async def receive(self, text_data: str | None = None, bytes_data: bytes | None = None) -> None:
        # A bridge client's data is live and already capped per client by the agent: not counted
        # against the robot's own frame rate, which is sized for its reports.
        if text_data is not None and self.authenticated and text_data.startswith(BRIDGE_FRAME_PREFIX):
            if self.closing:
                return
            try:
                envelope = protocol.decode(text_data, direction=self.direction)
            except protocol.ProtocolError as exc:
                await self.fail(exc.message, reply_to=None, field=exc.field, code=exc.code)
                return
            await self.dispatch_envelope(envelope)
            return
        if bytes_data is not None and self.authenticated and protocol.is_bridge_blob(bytes_data):
            # A frame several bridge clients share, sent once; their bridge_frames name it next.
            if self.closing:
                return
            try:
                self.bridges.take_blob(bytes_data)
            except protocol.ProtocolError as exc:
                await self.fail(exc.message, reply_to=None, field=exc.field, code=exc.code)
            return
        await super().receive(text_data, bytes_data)

    async def dispatch_envelope(self, envelope: Envelope) -> None:
        """Route one valid frame from the robot to its handler."""
        prometheus.frame_received()
        event = envelope.event
        forwarded = envelope.reply_to is not None and envelope.reply_to in self.requests
        if forwarded:
            await self.forward_reply(envelope)
        if event == Event.ACK:
            self.settled(envelope.reply_to)
            if envelope.reply_to in self.rekeys:
                self.rekeys.discard(envelope.reply_to)
                await sync(rotation.record_rekeyed)(self.robot_id)
            return
        if event == Event.ERROR_MESSAGE:
            # The robot refused a frame: sending it again would be refused again.
            self.settled(envelope.reply_to)
            self.rekeys.discard(envelope.reply_to)
        if envelope.reply_to is not None and envelope.reply_to in self.chunk_requests:
            future = self.chunk_requests[envelope.reply_to]
            if not future.done():
                future.set_result(envelope)
            return
        if event not in self.handlers:
            # A reply only its requester reads (components_api_reply): handed on above, or late, its
            # requester gone. Either way there is nothing to apply, and nothing wrong with the frame.
            if not forwarded:
                log.debug("robot %s: %s answers %s, which nobody waits for", self.robot_id, event, envelope.reply_to)
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
            prometheus.dedup_hit()
            await self.ack(envelope)
            return
        try:
            # Metrics and volume changes are kept from applying twice by their own stores.
            with applying(self.robot_id, envelope.id) if needs_ack and event not in OWN_DEDUP else nullcontext():
                ack_now = await self.handlers[event](self, envelope, payload)
        except AlreadyApplied:
            prometheus.dedup_hit()
            ack_now = True
        except NotFound as exc:
            self.dedup.forget(envelope.id)
            await self.fail(exc.message, reply_to=envelope.id, field=exc.field, code="not_found")
            return
        except ValidationError as exc:
            self.dedup.forget(envelope.id)
            message, field = validation_message(exc)
            await self.fail(message, reply_to=envelope.id, field=field, code="invalid_payload")
            return
        except Exception:
            self.dedup.forget(envelope.id)
            log.exception("robot %s: handling %s failed", self.robot_id, event)
            await self.fail("internal error, send again later", reply_to=envelope.id, code="internal_error")
            return
        if needs_ack and ack_now:
            applied_ids().add(self.robot_id, envelope.id)
            await self.ack_applied(envelope)

    async def ack_applied(self, envelope: Envelope) -> None:
        """Ack an applied frame once its id is saved where any server process finds it."""
        try:
            await applied_ids().flush()
        except Exception as exc:
            # Redis is down (so is the channel layer): ack anyway, the robot's link stays usable.
            saving_failures.failed(exc)
        else:
            saving_failures.worked()
        await self.ack(envelope)

    # ---------------------------------------------------------------- authentication

    async def authenticate(self, envelope: Envelope) -> bool:
        """Check the robot's id and token, mark it connected and send it its config."""
        try:
            return await self.log_in(envelope)
        finally:
            self.login_answered.set()

    async def log_in(self, envelope: Envelope) -> bool:
        """Answer the robot's login: refused, or authentication_success with its first frames."""
        credentials = protocol.parse_payload(envelope)
        problems = label_problems(credentials.labels or {})
        if problems:
            await self.refuse(f"invalid labels: {'; '.join(problems)}", reply_to=envelope.id)
            return False
        address = (self.scope.get("client") or ["?"])[0]
        presence = get_presence(self.channel_name)
        if presence is not None:
            # Registered before its first robot is marked connected here, so no sweep takes that for an orphan.
            await presence.joined()
        ros2 = None if credentials.ros2 is None else credentials.ros2.model_dump(mode="json")
        login = services.Login(
            credentials.robot,
            credentials.token,
            address,
            self.channel_name,
            credentials.ros_master,
            ros2,
            credentials.labels or None,
        )
        connected, reports, has_volumes = await login_queue().submit(login)
        if connected.blocked_s:
            await self.refuse("too many failed attempts; try again later", envelope.id, CLOSE_TOO_MANY_FAILURES)
            return False
        if connected.robot is None:
            await self.refuse("unknown robot or wrong token", reply_to=envelope.id)
            return False
        if presence is not None:
            presence.consumers.add(self)
        self.robot_id = connected.robot
        self.bridges.robot_id = connected.robot
        self.dedup.load(await applied_ids().load(connected.robot))
        if connected.replaced_channel:
            await self.channel_layer.send(connected.replaced_channel, {"type": "robot.replaced"})
        # One send for the login's frames, not one each: the robot reads them together too.
        with gathered_writes():
            await self.send_envelope(
                protocol.make(
                    Event.AUTHENTICATION_SUCCESS,
                    {
                        "robot": connected.robot,
                        "ros_master": connected.ros_master,
                        "ros2_discovery_server": connected.ros2_discovery_server,
                        "cloud_relays": connected.cloud_relays,
                    },
                    reply_to=envelope.id,
                    now=time.time(),
                )
            )
            await self.send_reliably(
                protocol.make(Event.CONNECTION_ESTABLISHED, {"robot": connected.robot}, now=time.time())
            )
            await self.send_reliably(protocol.make(Event.ROBOT_CONFIG, {"config": connected.config}, now=time.time()))
            # What became of its cloud copies while it was away (a start it waits for may have finished).
            for event, data in reports:
                await self.send_reliably(protocol.make(event, data, now=time.time()))
        if has_volumes:
            self.scan_volumes()
        return True

    # ---------------------------------------------------------------- Skill volumes

    @cached_property
    def volumes(self) -> CloudVolumes:
        """The robot's cloud volume replicas: made when first used, as most robots never have one."""
        if self.robot_id is None:
            raise RuntimeError("a robot has cloud volumes only once it has authenticated")
        return CloudVolumes(self.robot_id)

    def scan_volumes(self) -> None:
        """Announce the cloud copies' volume writes to the robot every second, from now on."""
        if self.volume_scanner is None:
            self.volume_scanner = self.spawn(self._scan_volumes_forever())

    async def _scan_volumes_forever(self) -> None:
        failures = LogOnce(log, f"robot {self.robot_id}: scanning its cloud volumes", traceback=True)
        while not self.closing:
            await asyncio.sleep(VOLUME_SCAN_S)
            try:
                for data in await self.volumes.scan():
                    await self.send_reliably(protocol.make(Event.VOLUME_CHANGES, data, now=time.time()))
            except Exception as exc:
                failures.failed(exc)
            else:
                failures.worked()

    async def ask_chunks(self, data: dict[str, Any]) -> Any:
        """Ask the robot for volume chunks and wait for its answer."""
        envelope = protocol.make(Event.VOLUME_CHUNKS_GET, data, now=time.time())
        future = self.chunk_requests[envelope.id] = asyncio.get_running_loop().create_future()
        try:
            await self.send_envelope(envelope)
            async with asyncio.timeout(CHUNK_WAIT_S):
                reply = await future
        finally:
            self.chunk_requests.pop(envelope.id, None)
        if reply.event != Event.VOLUME_CHUNKS:
            raise RuntimeError(f"the robot did not send the chunks: {reply.data.get('message', reply.event)}")
        return protocol.parse_payload(reply)

    # ---------------------------------------------------------------- commands from the cloud

    async def close_with(self, code: int, reason: str) -> None:
        self.login_answered.set()  # a login timed out or cut short: nothing waits on it (nor on a dispatch behind it)
        await super().close_with(code, reason)

    async def logged_in(self) -> bool:
        """Wait until the robot's login is answered; tell whether it is in and the socket still open."""
        await self.login_answered.wait()
        return self.robot_id is not None and not self.closing

    async def robot_command(self, message: dict[str, Any]) -> None:
        """Send a command relayed by relay_command, remembering who waits for the reply."""
        envelope = protocol.decode(message["frame"])
        if not await self.logged_in():
            await deliver(message["reply_channel"], {"type": "robot.reply", "offline": True, "id": envelope.id})
            return
        now = time.monotonic()
        self.requests[envelope.id] = (message["reply_channel"], now)
        while self.requests and (
            len(self.requests) > MAX_OPEN_REQUESTS or next(iter(self.requests.values()))[1] < now - REQUEST_TTL
        ):
            self.requests.popitem(last=False)
        await self.send_reliably(envelope)

    async def robot_push(self, message: dict[str, Any]) -> None:
        """Send a frame the cloud pushes to the robot (e.g. its cloud copies' status), until acked."""
        if await self.logged_in():
            await self.send_reliably(protocol.decode(message["frame"]))

    async def robot_rekey(self, message: dict[str, Any]) -> None:
        """Give the robot its new token (rotate_token with a grace), resent until it acks, which is logged."""
        envelope = protocol.decode(message["frame"])
        if not await self.logged_in():
            return  # it logs in with its new token, or its old one within the grace
        self.rekeys.add(envelope.id)
        await self.send_reliably(envelope)

    async def forward_reply(self, envelope: Envelope) -> None:
        """Hand the robot's answer to whoever relayed the command."""
        reply_channel, _ = self.requests.pop(envelope.reply_to)
        await deliver(reply_channel, {"type": "robot.reply", "frame": protocol.encode(envelope)})

    async def robot_bridge(self, message: dict[str, Any]) -> None:
        """Pass a bridge client's frame (or its session's opening or end) to the robot."""
        if not await self.logged_in():
            if message.get("open"):
                await deliver(message["open"], {"type": "bridge.closed", "offline": True})
            return
        await self.bridges.from_client(message, self.send_text)

    async def robot_revoked(self, message: dict[str, Any]) -> None:
        """Close this connection: the robot's token was rotated or the robot deleted."""
        await self.close_with(CLOSE_REVOKED, "credentials revoked")

    async def robot_replaced(self, message: dict[str, Any]) -> None:
        """Close this connection: the robot reconnected on a newer one."""
        await self.close_with(CLOSE_REPLACED, "replaced by a newer connection")

    def settled(self, frame_id: str | None) -> None:
        """Stop resending a frame the robot acked or refused; with nothing left, stop the resend timer."""
        if self.reliable.on_ack(frame_id) and not self.reliable and self.retransmit_timer is not None:
            # A timer left to fire would cost a callback a robot for nothing.
            self.retransmit_timer.cancel()
            self.retransmit_timer = None

    def _schedule_retransmit(self) -> None:
        if self.retransmit_timer is not None:
            self.retransmit_timer.cancel()
        due = self.reliable.next_due()
        if due is not None:
            delay = max(0.0, due - time.monotonic())
            self.retransmit_timer = asyncio.get_running_loop().call_later(delay, self.retransmit)

    def retransmit(self) -> None:
        """Resend every unacknowledged frame whose time has come."""
        self.retransmit_timer = None
        if self.closing:
            return
        due = self.reliable.due(time.monotonic())
        if due:
            self.spawn(self._resend(due))
        self._schedule_retransmit()

    async def _resend(self, envelopes: list[Envelope]) -> None:
        for envelope in envelopes:
            await self.send_envelope(envelope)

    # ---------------------------------------------------------------- closing

    async def closed(self, code: int) -> None:
        self.login_answered.set()  # what waits for a login that never came is told the robot is offline
        if self.retransmit_timer is not None:
            self.retransmit_timer.cancel()
        for request_id, (reply_channel, _) in self.requests.items():
            # The id: one relay waits on one reply channel for many robots' answers.
            await deliver(reply_channel, {"type": "robot.reply", "offline": True, "id": request_id})
        self.requests.clear()
        await self.bridges.robot_left()
        if self.robot_id is not None:
            reason = getattr(self, "close_reason", None) or f"connection closed (code {code})"
            await applied_ids().flush()
            await goodbye_queue().submit(services.Departure(self.robot_id, self.channel_name, reason))


def handles(*events: Event) -> Callable:
    """Register a RobotConsumer method as the handler of events."""

    def register(function: Callable) -> Callable:
        for event in events:
            RobotConsumer.handlers[event] = function
        return function

    return register


# Each handler applies one event and returns whether to ack it now (metrics ack after commit).


@handles(Event.METRICS)
async def on_metrics(consumer: RobotConsumer, envelope: Envelope, payload: Any) -> bool:
    points = payload.metrics
    if not points:
        return True
    prometheus.points_received(len(points))
    robot_id = consumer.robot_id
    store = applied_ids()
    written = store.in_flight(robot_id, envelope.id)
    if written is None:
        written = get_writer().add(robot_id, points, envelope.id)
        store.hold(robot_id, envelope.id, written)
        feed = get_live_feed()

        def broadcast(future: asyncio.Future) -> None:
            # Clients hear of points only once their rows are committed, never of points that were not stored.
            if not future.cancelled() and future.exception() is None:
                feed.add_metrics(robot_id, points)

        written.add_done_callback(broadcast)
    # else: an earlier connection's copy of this frame is still being written: answer with its outcome.

    def acknowledge(future: asyncio.Future) -> None:
        if future.cancelled() or future.exception() is not None:
            consumer.dedup.forget(envelope.id)
            consumer.spawn(
                consumer.fail("metrics not stored, send again later", reply_to=envelope.id, code="unavailable")
            )
        else:
            # Committed with its frame's row, which any process finds: no id to save elsewhere first.
            consumer.spawn(consumer.ack(envelope))

    written.add_done_callback(acknowledge)
    return False


@handles(Event.SKILL_STATUS)
async def on_skill_status(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(skills.report_skill_status)(consumer.robot_id, p.skill, p.status, p.message)
    return True


@handles(Event.COMPONENT_STATUS)
async def on_component_status(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    last_lines = None if p.last_lines is None else [line.model_dump(mode="json") for line in p.last_lines]
    await sync(skills.report_component_status)(
        consumer.robot_id, p.skill, p.component, p.status, p.location, p.message, last_lines=last_lines
    )
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


@handles(Event.OFFLOADING_DECISION)
async def on_offloading_decision(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(skills.report_offloading_decision)(consumer.robot_id, p)
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


@handles(Event.BRIDGE_FRAME, Event.BRIDGE_CLOSE)
async def on_bridge(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await consumer.bridges.from_robot(envelope.event, p)
    return False
