"""The Foxglove WebSocket protocol (v1), free of any transport: frames in, frames out through a send callback.

One ``Foxglove`` serves a robot's graph to many clients (Foxglove, Lichtblick, the
``@foxglove/ws-protocol`` client); each client is a ``FoxgloveSession`` fed with the frames it
sends (JSON text, or binary with a one-byte opcode) and writing its answers through the async
``send`` it was given. The WebSocket door (``bridges.server``) is a thin adapter, and the cloud's
per-robot relay can feed the same sessions over the robot's own connection.

The graph's published topics are polled and offered as channels (``advertise``, ``unadvertise``
when the last publisher of one goes) with their full definitions as schemas: ROS 1 topics as
``ros1`` messages with ``ros1msg`` schemas, ROS 2 topics as ``cdr`` with ``ros2msg``. A subscribed
channel's messages go out as the raw bytes the graph carried, never decoded. A graph subscription
is shared by every client of a topic, and each client's subscription has its own bounded queue
(``bridges.fanout``).
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import itertools
import json
import logging
import os
import struct
import uuid
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Any

from bridgeos_agent.bridges.fanout import (
    BATCH_FRAMES,
    DEFAULT_QUEUE,
    LINGER_S,
    Fanouts,
    Outlet,
    Publishers,
    Send,
    SendMany,
    SharedTail,
    one_by_one,
)
from bridgeos_agent.bridges.foxgloveclock import CAPABILITY as TIME_CAPABILITY
from bridgeos_agent.bridges.foxgloveclock import SimClock
from bridgeos_agent.bridges.foxgloveparams import CAPABILITIES as PARAMETER_CAPABILITIES
from bridgeos_agent.bridges.foxgloveparams import PARAM_POLL_S, ParameterOps, ParameterWatch
from bridgeos_agent.bridges.foxglovepublish import ClientChannels
from bridgeos_agent.bridges.foxglovewire import (
    CLIENT_MESSAGE_DATA,
    ERROR,
    MESSAGE_DATA,
    SERVICE_CALL_REQUEST,
    SERVICE_CALL_RESPONSE,
    SUBPROTOCOLS,
    TIME,
    WARNING,
    Channel,
    Fail,
    Service,
    encode,
    ident_field,
    items_field,
    json_default,
    select_subprotocol,
)
from bridgeos_agent.bridges.graph import BridgeError, BridgeGraph, Sample

__all__ = ["SUBPROTOCOLS", "Foxglove", "FoxgloveSession", "select_subprotocol"]

logger = logging.getLogger(__name__)

CAPABILITIES = ("clientPublish", "services")
MAX_FRAME_BYTES = 16 << 20  # a frame bigger than this is refused with a status, the connection kept
CONTROL_QUEUE = 1_000  # JSON answers and statuses waiting for a client that does not read
MAX_SUBSCRIPTIONS = 1_000  # subscriptions one client may hold
MAX_CALLS_IN_FLIGHT = 64  # service calls one client may have running at once
CALL_TIMEOUT = 30.0
POLL_S = 2.0  # how often the graph's topics and services are looked at for channels come and gone
_UNSUPPORTED = (
    "subscribeConnectionGraph",
    "unsubscribeConnectionGraph",
    "fetchAsset",
)


class Foxglove:
    """Serve one robot graph to any number of Foxglove WebSocket clients."""

    def __init__(
        self,
        graph: BridgeGraph,
        *,
        name: str = "bridgeOS",
        max_frame_bytes: int = MAX_FRAME_BYTES,
        default_queue: int = DEFAULT_QUEUE,
        linger_s: float = LINGER_S,
        poll_s: float = POLL_S,
        call_timeout: float = CALL_TIMEOUT,
        param_poll_s: float = PARAM_POLL_S,
    ) -> None:
        self.graph = graph
        self.name = name
        self.max_frame_bytes = max_frame_bytes
        self.default_queue = default_queue
        self.poll_s = poll_s
        self.call_timeout = call_timeout
        self.session_id = uuid.uuid4().hex
        self.encodings = [graph.message_encoding, "json"]
        self.sessions: set[FoxgloveSession] = set()
        self.fanouts = Fanouts(graph, linger_s=linger_s)
        self.publishers = Publishers(graph)
        self.channels: dict[int, Channel] = {}
        self.services: dict[int, Service] = {}
        # Ids stay with a (topic, type) or (service, type) for the bridge's life, so one that comes back
        # gets its old id (the protocol allows reuse only for the very same channel).
        self._channel_ids: dict[tuple[str, str], int] = {}
        self._service_ids: dict[tuple[str, str], int] = {}
        self._next_id = itertools.count(1)
        self._unreadable: set[str] = set()  # types whose definitions were not found, told to the log once
        self._poller: asyncio.Task[None] | None = None
        self._poll_now = asyncio.Event()
        self._polled = asyncio.Event()
        self.parameters = ParameterWatch(graph, param_poll_s)
        self.clock = SimClock(graph, self._tell_time)
        self._clock_known = False  # a client is greeted once the graph's clock has been looked at

    def session(self, send: Send, send_many: SendMany | None = None) -> FoxgloveSession:
        """Open a session for a new client whose frames go out through ``send`` (or ``send_many``, several at once)."""
        session = FoxgloveSession(self, send, send_many)
        self.sessions.add(session)
        if self._clock_known:
            session.greet()
        if self._poller is None:
            self._poller = asyncio.get_running_loop().create_task(self._poll(), name="foxglove-graph-poll")
        self._poll_now.set()
        return session

    async def close(self) -> None:
        """Close every session and leave the graph's topics."""
        if self._poller is not None:
            self._poller.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._poller
            self._poller = None
        for session in list(self.sessions):
            await session.close()
        await self.parameters.stop()
        self.clock.close()
        self.fanouts.close()

    def forget(self, session: FoxgloveSession) -> None:
        """Drop a closed session."""
        self.sessions.discard(session)

    async def wait_polled(self) -> None:
        """Wait until the graph has been looked at once."""
        await self._polled.wait()

    # ------------------------------------------------------------------ channels and services

    def _tell_time(self, nanoseconds: int) -> None:
        for session in self.sessions:
            session.tell_time(nanoseconds)

    async def _poll(self) -> None:
        failing = False
        while True:
            # First the clock, since a client is offered the time capability (or not) in its greeting.
            try:
                await self.clock.check()
            except Exception:  # the greeting must not wait for a clock that cannot be read
                if not failing:
                    logger.exception("foxglove: cannot tell whether the graph runs on simulated time")
            if not self._clock_known:
                self._clock_known = True
                for session in list(self.sessions):
                    session.greet()
            try:
                await self.refresh()
            except BridgeError as exc:  # the master is gone for a while: say so once, keep the channels
                if not failing:
                    logger.warning("foxglove: cannot read the ROS graph: %s", exc)
                failing = True
            else:
                failing = False
            self._polled.set()
            self._poll_now.clear()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._poll_now.wait(), self.poll_s)

    async def refresh(self) -> None:
        """Offer the graph's topics and services as they are now: new ones advertised, gone ones withdrawn."""
        topics = await self.graph.published_topics()
        services = await self.graph.services()
        current = {(c.topic, c.type): c for c in self.channels.values()}
        gone = [c.id for key, c in current.items() if topics.get(key[0]) != key[1]]
        for channel_id in gone:
            del self.channels[channel_id]
        added = []
        for topic, type_ in sorted(topics.items()):
            if (topic, type_) in current:
                continue
            schema = self._schema(type_, functools.partial(self.graph.schema, type_))
            if schema is None:
                continue
            channel_id = self._channel_ids.setdefault((topic, type_), next(self._next_id))
            channel = Channel(channel_id, topic, type_, self.graph.message_encoding, self.graph.schema_encoding, schema)
            self.channels[channel_id] = channel
            added.append(channel)
        known = {(s.name, s.type): s for s in self.services.values()}
        gone_services = [s.id for key, s in known.items() if services.get(key[0]) != key[1]]
        for service_id in gone_services:
            del self.services[service_id]
        added_services = []
        for name, type_ in sorted(services.items()):
            if not type_ or (name, type_) in known:
                continue
            schemas = self._schema(type_, functools.partial(self.graph.service_schemas, type_))
            if schemas is None:
                continue
            service_id = self._service_ids.setdefault((name, type_), next(self._next_id))
            service = Service(service_id, name, type_, self.graph.message_encoding, self.graph.schema_encoding, schemas)
            self.services[service_id] = service
            added_services.append(service)
        for session in list(self.sessions):
            session.update(gone, added, gone_services, added_services)

    def _schema(self, type_: str, read: Callable[[], Any]) -> Any:
        try:
            return read()
        except BridgeError as exc:
            if type_ not in self._unreadable:
                self._unreadable.add(type_)
                logger.warning("foxglove: not offering what is of type %s: %s", type_, exc)
            return None

    # ------------------------------------------------------------------ service calls

    async def call(self, service: Service, encoding: str, payload: bytes) -> bytes:
        """Call a graph service with a request in ``encoding`` and return the response in the same."""
        if encoding == "json":
            try:
                args = json.loads(payload) if payload else {}
            except ValueError as exc:
                raise BridgeError(f"the request is not JSON: {exc}") from None
            if not isinstance(args, dict):
                raise BridgeError("a JSON request must be an object with the request's fields")
            answer = await self.graph.call_service(service.name, service.type, args, self.call_timeout)
            return json.dumps(answer, default=json_default, separators=(",", ":")).encode()
        return await self.graph.call_service_raw(service.name, service.type, payload, self.call_timeout)


class _Subscription(Outlet):
    """One subscription of a client: the channel it reads and its queue."""

    __slots__ = ("channel", "id")

    def __init__(self, ident: int, channel: Channel, size: int) -> None:
        super().__init__(channel.topic, size)
        self.id = ident
        self.channel = channel.id


class FoxgloveSession:
    """One Foxglove WebSocket client: parse its frames, run its requests, queue what goes back to it."""

    def __init__(self, bridge: Foxglove, send: Send, send_many: SendMany | None = None) -> None:
        self.bridge = bridge
        self.graph = bridge.graph
        self._send = send
        self._send_many = send_many or one_by_one(send)
        self._control: deque[str | bytes] = deque()
        self.control_dropped = 0
        self._subscriptions: dict[int, _Subscription] = {}
        self._by_channel: dict[int, int] = {}  # channel id -> this client's subscription id of it
        self._order: list[_Subscription] = []
        self._calls: set[asyncio.Task[None]] = set()
        self._wake = asyncio.Event()
        self.closed = False
        self.greeted = False  # nothing goes out before serverInfo, which waits for the graph's clock
        self.time = False  # offered the time capability: told the simulated time, stamped with it
        self._time_ns: int | None = None  # the latest time not yet sent
        self.parameters = ParameterOps(self, bridge.parameters)
        self.client_channels = ClientChannels(self)
        self._handlers: dict[str, Callable[[dict[str, Any]], Awaitable[None]]] = {
            "subscribe": self._subscribe,
            "unsubscribe": self._unsubscribe,
            **self.client_channels.handlers(),
            **self.parameters.handlers(),
        }

    def greet(self) -> None:
        """Send serverInfo and what the server offers now, ahead of anything already answered."""
        if self.greeted:
            return
        bridge = self.bridge
        self.greeted = True
        self.time = bridge.clock.active
        metadata = {"ROS_VERSION": str(self.graph.ros_version)}
        if os.environ.get("ROS_DISTRO"):
            metadata["ROS_DISTRO"] = os.environ["ROS_DISTRO"]
        info = {
            "op": "serverInfo",
            "name": bridge.name,
            "capabilities": [*CAPABILITIES, *PARAMETER_CAPABILITIES, *([TIME_CAPABILITY] if self.time else [])],
            "supportedEncodings": bridge.encodings,
            "metadata": metadata,
            "sessionId": bridge.session_id,
        }
        greeting: list[dict[str, Any]] = [
            info,
            {"op": "advertise", "channels": [c.advertisement() for c in bridge.channels.values()]},
        ]
        if bridge.services:
            greeting.append(
                {"op": "advertiseServices", "services": [s.advertisement() for s in bridge.services.values()]}
            )
        self._control.extendleft(encode(message) for message in reversed(greeting))
        if self.time and bridge.clock.now_ns is not None:
            self.tell_time(bridge.clock.now_ns)
        self._wake.set()

    # ------------------------------------------------------------------ frames in

    async def receive(self, data: str | bytes) -> None:
        """Handle one frame from the client; every fault is answered with a status, never raised."""
        if len(data) > self.bridge.max_frame_bytes:
            self.status(ERROR, f"frame of {len(data)} bytes exceeds the limit of {self.bridge.max_frame_bytes}")
            return
        if isinstance(data, str):
            await self._receive_text(data)
        else:
            await self._receive_binary(bytes(data))

    async def _receive_text(self, data: str) -> None:
        try:
            message = json.loads(data)
        except ValueError as exc:
            self.status(ERROR, f"malformed JSON: {exc}")
            return
        if not isinstance(message, dict) or not isinstance(message.get("op"), str):
            self.status(ERROR, "a text frame must be a JSON object with an 'op' string")
            return
        op = message["op"]
        handler = self._handlers.get(op)
        if handler is None:
            if op in _UNSUPPORTED:
                offered = ", ".join([*CAPABILITIES, *PARAMETER_CAPABILITIES, *([TIME_CAPABILITY] if self.time else [])])
                self.status(ERROR, f"{op} is not supported: this server's capabilities are {offered}")
            else:
                self.status(ERROR, f"unknown op {op[:64]!r}")
            return
        await self._guard(op, handler(message))

    async def _receive_binary(self, data: bytes) -> None:
        if not data:
            self.status(ERROR, "an empty binary frame has no opcode")
            return
        opcode = data[0]
        if opcode == CLIENT_MESSAGE_DATA:
            await self._guard("client message data", self.client_channels.message(data))
        elif opcode == SERVICE_CALL_REQUEST:
            await self._guard("service call request", self._service_call(data))
        else:
            self.status(ERROR, f"unknown binary opcode 0x{opcode:02x}")

    async def _guard(self, what: str, work: Awaitable[None]) -> None:
        try:
            await work
        except Fail as exc:
            self.status(exc.level, f"{what}: {exc}")
        except BridgeError as exc:
            self.status(ERROR, f"{what}: {exc}")
        except Exception as exc:  # a fault of ours must cost the client one answer, not its connection
            logger.exception("foxglove: %s failed", what)
            self.status(ERROR, f"{what}: internal error: {type(exc).__name__}: {exc}"[:500])

    async def _subscribe(self, message: dict[str, Any]) -> None:
        for item in items_field(message, "subscriptions"):
            try:
                await self._subscribe_one(item)
            except BridgeError as exc:
                self.status(getattr(exc, "level", ERROR), f"subscribe: {exc}")

    async def _subscribe_one(self, item: Any) -> None:
        if not isinstance(item, dict):
            raise Fail("each subscription must be an object with 'id' and 'channelId'")
        ident = ident_field(item.get("id"), "a subscription's 'id'")
        channel_id = ident_field(item.get("channelId"), "'channelId'")
        if ident in self._subscriptions:
            raise Fail(f"subscription id {ident} is already in use")
        channel = self.bridge.channels.get(channel_id)
        if channel is None:
            raise Fail(f"no channel {channel_id} is advertised")
        if channel_id in self._by_channel:
            taken = self._by_channel[channel_id]
            raise Fail(f"channel {channel_id} ({channel.topic}) is already subscribed as {taken}")
        if len(self._subscriptions) >= MAX_SUBSCRIPTIONS:
            raise Fail(f"a client may hold at most {MAX_SUBSCRIPTIONS} subscriptions")
        subscription = _Subscription(ident, channel, self.bridge.default_queue)
        self._subscriptions[ident] = subscription
        self._by_channel[channel_id] = ident
        try:
            await self.bridge.fanouts.attach(channel.topic, channel.type, subscription, self)
        except BaseException:
            self._subscriptions.pop(ident, None)
            self._by_channel.pop(channel_id, None)
            raise
        if self.closed or self._subscriptions.get(ident) is not subscription:  # gone while subscribing
            self.bridge.fanouts.detach(channel.topic, subscription)
            return
        self._order.append(subscription)

    async def _unsubscribe(self, message: dict[str, Any]) -> None:
        for value in items_field(message, "subscriptionIds"):
            try:
                ident = ident_field(value, "a subscription id")
                subscription = self._subscriptions.get(ident)
                if subscription is None:
                    raise Fail(f"no subscription {ident}", WARNING)
                self._drop_subscription(subscription)
            except Fail as exc:
                self.status(exc.level, f"unsubscribe: {exc}")

    def _drop_subscription(self, subscription: _Subscription) -> None:
        self._subscriptions.pop(subscription.id, None)
        self._by_channel.pop(subscription.channel, None)
        with contextlib.suppress(ValueError):
            self._order.remove(subscription)
        self.bridge.fanouts.detach(subscription.topic, subscription)

    async def _service_call(self, data: bytes) -> None:
        if len(data) < 13:
            raise Fail(f"{len(data)} bytes: too short for a service call request")
        service_id, call_id, size = struct.unpack_from("<III", data, 1)
        if 13 + size > len(data):
            raise Fail(f"the encoding's length {size} runs past the frame's end")
        encoding = data[13 : 13 + size].decode("utf-8", "replace")
        payload = data[13 + size :]
        service = self.bridge.services.get(service_id)
        if service is None:
            self.call_failure(service_id, call_id, f"no service {service_id} is advertised")
            return
        if encoding not in self.bridge.encodings:
            self.call_failure(
                service_id, call_id, f"encoding {encoding[:32]!r} is not one of {', '.join(self.bridge.encodings)}"
            )
            return
        if len(self._calls) >= MAX_CALLS_IN_FLIGHT:
            self.call_failure(service_id, call_id, f"{MAX_CALLS_IN_FLIGHT} service calls are already running")
            return
        task = asyncio.get_running_loop().create_task(self._run_call(service, call_id, encoding, payload))
        self._calls.add(task)
        task.add_done_callback(self._calls.discard)

    async def _run_call(self, service: Service, call_id: int, encoding: str, payload: bytes) -> None:
        try:
            answer = await asyncio.wait_for(self.bridge.call(service, encoding, payload), self.bridge.call_timeout + 1)
        except BridgeError as exc:
            self.call_failure(service.id, call_id, f"{service.name}: {exc}")
        except TimeoutError:
            self.call_failure(service.id, call_id, f"{service.name} did not answer in time")
        else:
            name = encoding.encode()
            head = struct.pack("<BIII", SERVICE_CALL_RESPONSE, service.id, call_id, len(name))
            self._queue(head + name + answer)

    # ------------------------------------------------------------------ graph changes

    def tell_time(self, nanoseconds: int) -> None:
        """Send the simulated time (only the latest waits) if this client was offered the time capability."""
        if self.time and not self.closed:
            self._time_ns = nanoseconds
            self._wake.set()

    def update(
        self, gone: list[int], added: list[Channel], gone_services: list[int], added_services: list[Service]
    ) -> None:
        """Tell the client of channels and services come and gone; end its subscriptions of gone channels."""
        for channel_id in gone:
            ident = self._by_channel.get(channel_id)
            if ident is not None:
                self._drop_subscription(self._subscriptions[ident])
        if not self.greeted:  # its greeting will offer what there is then
            return
        if gone:
            self.send({"op": "unadvertise", "channelIds": gone})
        if added:
            self.send({"op": "advertise", "channels": [c.advertisement() for c in added]})
        if gone_services:
            self.send({"op": "unadvertiseServices", "serviceIds": gone_services})
        if added_services:
            self.send({"op": "advertiseServices", "services": [s.advertisement() for s in added_services]})

    # ------------------------------------------------------------------ frames out

    def status(self, level: int, text: str) -> None:
        """Tell the client something (0 info, 1 warning, 2 error)."""
        self.send({"op": "status", "level": level, "message": text})

    def call_failure(self, service_id: int, call_id: int, text: str) -> None:
        """Tell the client a service call failed."""
        self.send({"op": "serviceCallFailure", "serviceId": service_id, "callId": call_id, "message": text})

    def send(self, message: dict[str, Any]) -> None:
        """Queue a JSON protocol message for the client."""
        self._queue(encode(message))

    def _queue(self, frame: str | bytes) -> None:
        if self.closed:
            return
        if len(self._control) >= CONTROL_QUEUE:
            self._control.popleft()
            self.control_dropped += 1
        self._control.append(frame)
        self._wake.set()

    def wake(self) -> None:
        """Tell the writer there is something to send."""
        self._wake.set()

    def stats(self) -> dict[str, dict[str, int]]:
        """Return each subscribed topic's messages sent, dropped and queued for this client."""
        return {s.topic: {"sent": s.sent, "dropped": s.dropped, "queued": len(s.queue)} for s in self._order}

    async def run(self) -> None:
        """Write queued frames to the client until the session closes (the door runs this beside its reader)."""
        while not self.closed:
            frame = self._take()
            if frame is not None:
                # Everything ready goes in one go: a door writes a batch to its socket at once.
                frames = [frame]
                while len(frames) < BATCH_FRAMES and (frame := self._take()) is not None:
                    frames.append(frame)
                await self._send_many(frames)
                continue
            self._wake.clear()
            await self._wake.wait()

    def _take(self) -> str | bytes | None:
        if not self.greeted:
            return None
        if self._control:
            return self._control.popleft()
        if self._time_ns is not None:
            frame, self._time_ns = struct.pack("<BQ", TIME, self._time_ns), None
            return frame
        order = self._order
        for index, subscription in enumerate(order):
            if not subscription.queue:
                continue
            sample: Sample = subscription.queue.popleft()
            # Round robin: the subscription just served goes last, so a busy topic cannot starve the others.
            order.append(order.pop(index))
            subscription.sent += 1
            if self.time:  # the protocol wants the time frames' source for message stamps too
                stamp = self.bridge.clock.stamp(sample)
            else:
                seconds, nanoseconds = sample.stamp
                stamp = seconds * 1_000_000_000 + nanoseconds
            head = struct.pack("<BIQ", MESSAGE_DATA, subscription.id, stamp)
            return SharedTail(head, sample.raw)
        return None

    # ------------------------------------------------------------------ end

    async def close(self) -> None:
        """Undo everything the client did in the graph."""
        if self.closed:
            return
        self.closed = True
        self._wake.set()
        for subscription in list(self._subscriptions.values()):
            self._drop_subscription(subscription)
        self.client_channels.close()
        for task in list(self._calls):
            task.cancel()
        await asyncio.gather(*self._calls, return_exceptions=True)
        await self.parameters.close()
        self.bridge.forget(self)
