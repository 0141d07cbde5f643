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
from collections.abc import Awaitable, Callable, Iterable
from dataclasses import dataclass, field
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
from bridgeos_agent.bridges.graph import BridgeError, BridgeGraph, GraphPublisher, Sample

__all__ = ["SUBPROTOCOLS", "Foxglove", "FoxgloveSession", "select_subprotocol"]

logger = logging.getLogger(__name__)

# The Foxglove app offers foxglove.websocket.v1; the Foxglove SDK's clients offer foxglove.sdk.v1 for
# the same messages. A door (or the cloud relay) answers with the one the client offered first.
SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
CAPABILITIES = ("clientPublish", "services")
MAX_FRAME_BYTES = 16 << 20  # a frame bigger than this is refused with a status, the connection kept
CONTROL_QUEUE = 1_000  # JSON answers and statuses waiting for a client that does not read
MAX_SUBSCRIPTIONS = 1_000  # subscriptions one client may hold
MAX_CLIENT_CHANNELS = 256  # channels one client may advertise
MAX_CALLS_IN_FLIGHT = 64  # service calls one client may have running at once
CALL_TIMEOUT = 30.0
POLL_S = 2.0  # how often the graph's topics and services are looked at for channels come and gone
MAX_ID = 2**32 - 1

# Binary opcodes: from the server, and from the client.
MESSAGE_DATA = 0x01
SERVICE_CALL_RESPONSE = 0x03
CLIENT_MESSAGE_DATA = 0x01
SERVICE_CALL_REQUEST = 0x02

INFO, WARNING, ERROR = 0, 1, 2
_UNSUPPORTED = (
    "getParameters",
    "setParameters",
    "subscribeParameterUpdates",
    "unsubscribeParameterUpdates",
    "subscribeConnectionGraph",
    "unsubscribeConnectionGraph",
    "fetchAsset",
)


def select_subprotocol(offered: Iterable[str]) -> str | None:
    """Return the first subprotocol a client offers that this protocol speaks, or None."""
    return next((name for name in offered if name in SUBPROTOCOLS), None)


def encode(message: dict[str, Any]) -> str:
    """Encode a JSON protocol message."""
    return json.dumps(message, separators=(",", ":"))


class _Fail(BridgeError):
    """A client's request that is refused, at a level (error unless said)."""

    def __init__(self, message: str, level: int = ERROR) -> None:
        super().__init__(message)
        self.level = level


def _ident(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_ID:
        raise _Fail(f"{what} must be an integer in 0..{MAX_ID}, not {value!r}"[:200])
    return value


def _items(message: dict[str, Any], key: str) -> list[Any]:
    value = message.get(key)
    if not isinstance(value, list):
        raise _Fail(f"'{key}' must be an array" if key in message else f"'{key}' is missing")
    return value


@dataclass
class Channel:
    """A topic of the graph offered to clients."""

    id: int
    topic: str
    type: str
    encoding: str
    schema_encoding: str
    schema: str

    def advertisement(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "topic": self.topic,
            "encoding": self.encoding,
            "schemaName": self.type,
            "schemaEncoding": self.schema_encoding,
            "schema": self.schema,
        }


@dataclass
class Service:
    """A service of the graph offered to clients."""

    id: int
    name: str
    type: str
    encoding: str
    schema_encoding: str
    schemas: tuple[str, str]

    def advertisement(self) -> dict[str, Any]:
        def part(suffix: str, schema: str) -> dict[str, str]:
            return {
                "encoding": self.encoding,
                "schemaName": self.type + suffix,
                "schemaEncoding": self.schema_encoding,
                "schema": schema,
            }

        return {
            "id": self.id,
            "name": self.name,
            "type": self.type,
            "request": part("_Request", self.schemas[0]),
            "response": part("_Response", self.schemas[1]),
            # Older clients read only these; the schema encoding is then taken from supportedEncodings.
            "requestSchema": self.schemas[0],
            "responseSchema": self.schemas[1],
        }


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

    def session(self, send: Send, send_many: SendMany | None = None) -> FoxgloveSession:
        """Open a session for a new client whose frames go out through ``send`` (or ``send_many``, several at once)."""
        session = FoxgloveSession(self, send, send_many)
        self.sessions.add(session)
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
        self.fanouts.close()

    def forget(self, session: FoxgloveSession) -> None:
        """Drop a closed session."""
        self.sessions.discard(session)

    async def wait_polled(self) -> None:
        """Wait until the graph has been looked at once."""
        await self._polled.wait()

    # ------------------------------------------------------------------ channels and services

    async def _poll(self) -> None:
        failing = False
        while True:
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
            return json.dumps(answer, default=_json_default, separators=(",", ":")).encode()
        return await self.graph.call_service_raw(service.name, service.type, payload, self.call_timeout)


def _json_default(value: Any) -> Any:
    if isinstance(value, bytes | bytearray | memoryview):
        return list(bytes(value))
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


class _Subscription(Outlet):
    """One subscription of a client: the channel it reads and its queue."""

    __slots__ = ("channel", "id")

    def __init__(self, ident: int, channel: Channel, size: int) -> None:
        super().__init__(channel.topic, size)
        self.id = ident
        self.channel = channel.id


@dataclass
class _ClientChannel:
    topic: str
    encoding: str
    publisher: GraphPublisher
    published: int = field(default=0)


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
        self._client_channels: dict[int, _ClientChannel] = {}
        self._calls: set[asyncio.Task[None]] = set()
        self._wake = asyncio.Event()
        self.closed = False
        self._handlers: dict[str, Callable[[dict[str, Any]], Awaitable[None]]] = {
            "subscribe": self._subscribe,
            "unsubscribe": self._unsubscribe,
            "advertise": self._advertise,
            "unadvertise": self._unadvertise,
        }
        metadata = {"ROS_VERSION": str(self.graph.ros_version)}
        if os.environ.get("ROS_DISTRO"):
            metadata["ROS_DISTRO"] = os.environ["ROS_DISTRO"]
        self.send(
            {
                "op": "serverInfo",
                "name": bridge.name,
                "capabilities": list(CAPABILITIES),
                "supportedEncodings": bridge.encodings,
                "metadata": metadata,
                "sessionId": bridge.session_id,
            }
        )
        self.send({"op": "advertise", "channels": [c.advertisement() for c in bridge.channels.values()]})
        if bridge.services:
            self.send({"op": "advertiseServices", "services": [s.advertisement() for s in bridge.services.values()]})

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
                self.status(ERROR, f"{op} is not supported: this server's capabilities are {', '.join(CAPABILITIES)}")
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
            await self._guard("client message data", self._client_message(data))
        elif opcode == SERVICE_CALL_REQUEST:
            await self._guard("service call request", self._service_call(data))
        else:
            self.status(ERROR, f"unknown binary opcode 0x{opcode:02x}")

    async def _guard(self, what: str, work: Awaitable[None]) -> None:
        try:
            await work
        except _Fail as exc:
            self.status(exc.level, f"{what}: {exc}")
        except BridgeError as exc:
            self.status(ERROR, f"{what}: {exc}")
        except Exception as exc:  # a fault of ours must cost the client one answer, not its connection
            logger.exception("foxglove: %s failed", what)
            self.status(ERROR, f"{what}: internal error: {type(exc).__name__}: {exc}"[:500])

    async def _subscribe(self, message: dict[str, Any]) -> None:
        for item in _items(message, "subscriptions"):
            try:
                await self._subscribe_one(item)
            except BridgeError as exc:
                self.status(getattr(exc, "level", ERROR), f"subscribe: {exc}")

    async def _subscribe_one(self, item: Any) -> None:
        if not isinstance(item, dict):
            raise _Fail("each subscription must be an object with 'id' and 'channelId'")
        ident = _ident(item.get("id"), "a subscription's 'id'")
        channel_id = _ident(item.get("channelId"), "'channelId'")
        if ident in self._subscriptions:
            raise _Fail(f"subscription id {ident} is already in use")
        channel = self.bridge.channels.get(channel_id)
        if channel is None:
            raise _Fail(f"no channel {channel_id} is advertised")
        if channel_id in self._by_channel:
            taken = self._by_channel[channel_id]
            raise _Fail(f"channel {channel_id} ({channel.topic}) is already subscribed as {taken}")
        if len(self._subscriptions) >= MAX_SUBSCRIPTIONS:
            raise _Fail(f"a client may hold at most {MAX_SUBSCRIPTIONS} subscriptions")
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
        for value in _items(message, "subscriptionIds"):
            try:
                ident = _ident(value, "a subscription id")
                subscription = self._subscriptions.get(ident)
                if subscription is None:
                    raise _Fail(f"no subscription {ident}", WARNING)
                self._drop_subscription(subscription)
            except _Fail as exc:
                self.status(exc.level, f"unsubscribe: {exc}")

    def _drop_subscription(self, subscription: _Subscription) -> None:
        self._subscriptions.pop(subscription.id, None)
        self._by_channel.pop(subscription.channel, None)
        with contextlib.suppress(ValueError):
            self._order.remove(subscription)
        self.bridge.fanouts.detach(subscription.topic, subscription)

    async def _advertise(self, message: dict[str, Any]) -> None:
        for item in _items(message, "channels"):
            try:
                await self._advertise_one(item)
            except BridgeError as exc:
                self.status(getattr(exc, "level", ERROR), f"advertise: {exc}")

    async def _advertise_one(self, item: Any) -> None:
        if not isinstance(item, dict):
            raise _Fail("each channel must be an object with 'id', 'topic', 'encoding' and 'schemaName'")
        ident = _ident(item.get("id"), "a channel's 'id'")
        topic, encoding, type_ = item.get("topic"), item.get("encoding"), item.get("schemaName")
        for key, value in (("topic", topic), ("encoding", encoding), ("schemaName", type_)):
            if not isinstance(value, str) or not value:
                raise _Fail(f"channel {ident}: '{key}' must be a non-empty string")
        assert isinstance(topic, str) and isinstance(encoding, str) and isinstance(type_, str)
        if len(topic) > 256 or any(ch.isspace() for ch in topic):
            raise _Fail(f"channel {ident}: {topic[:64]!r} is not a ROS topic name")
        topic = topic if topic.startswith("/") else "/" + topic
        if encoding not in self.bridge.encodings:
            raise _Fail(f"channel {ident}: encoding {encoding[:32]!r} is not one of {', '.join(self.bridge.encodings)}")
        if ident in self._client_channels:
            raise _Fail(f"channel id {ident} is already advertised by this client")
        if len(self._client_channels) >= MAX_CLIENT_CHANNELS:
            raise _Fail(f"a client may advertise at most {MAX_CLIENT_CHANNELS} channels")
        publisher = await self.bridge.publishers.advertise(topic, type_, (self, ident))
        self._client_channels[ident] = _ClientChannel(topic, encoding, publisher)

    async def _unadvertise(self, message: dict[str, Any]) -> None:
        for value in _items(message, "channelIds"):
            try:
                ident = _ident(value, "a channel id")
                channel = self._client_channels.pop(ident, None)
                if channel is None:
                    raise _Fail(f"channel {ident} is not advertised by this client", WARNING)
                self.bridge.publishers.unadvertise(channel.topic, (self, ident))
            except _Fail as exc:
                self.status(exc.level, f"unadvertise: {exc}")

    async def _client_message(self, data: bytes) -> None:
        if len(data) < 5:
            raise _Fail(f"{len(data)} bytes: too short for a channel id")
        (ident,) = struct.unpack_from("<I", data, 1)
        channel = self._client_channels.get(ident)
        if channel is None:
            raise _Fail(f"channel {ident} is not advertised by this client")
        payload = data[5:]
        if channel.encoding == "json":
            try:
                msg = json.loads(payload)
            except ValueError as exc:
                raise _Fail(f"{channel.topic}: the message is not JSON: {exc}") from None
            if not isinstance(msg, dict):
                raise _Fail(f"{channel.topic}: a JSON message must be an object")
            channel.publisher.publish(msg)
        else:
            try:
                channel.publisher.publish_raw(payload)
            except BridgeError as exc:
                raise _Fail(f"{channel.topic}: {exc}") from None
        channel.published += 1

    async def _service_call(self, data: bytes) -> None:
        if len(data) < 13:
            raise _Fail(f"{len(data)} bytes: too short for a service call request")
        service_id, call_id, size = struct.unpack_from("<III", data, 1)
        if 13 + size > len(data):
            raise _Fail(f"the encoding's length {size} runs past the frame's end")
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

    def update(
        self, gone: list[int], added: list[Channel], gone_services: list[int], added_services: list[Service]
    ) -> None:
        """Tell the client of channels and services come and gone; end its subscriptions of gone channels."""
        for channel_id in gone:
            ident = self._by_channel.get(channel_id)
            if ident is not None:
                self._drop_subscription(self._subscriptions[ident])
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
        if self._control:
            return self._control.popleft()
        order = self._order
        for index, subscription in enumerate(order):
            if not subscription.queue:
                continue
            sample: Sample = subscription.queue.popleft()
            # Round robin: the subscription just served goes last, so a busy topic cannot starve the others.
            order.append(order.pop(index))
            subscription.sent += 1
            seconds, nanoseconds = sample.stamp
            head = struct.pack("<BIQ", MESSAGE_DATA, subscription.id, seconds * 1_000_000_000 + nanoseconds)
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
        for ident, channel in list(self._client_channels.items()):
            self.bridge.publishers.unadvertise(channel.topic, (self, ident))
        self._client_channels.clear()
        for task in list(self._calls):
            task.cancel()
        await asyncio.gather(*self._calls, return_exceptions=True)
        self.bridge.forget(self)
