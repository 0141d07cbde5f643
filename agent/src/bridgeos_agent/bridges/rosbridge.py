"""The rosbridge v2 protocol, free of any transport: frames in, frames out through a send callback.

One ``Rosbridge`` serves a robot's graph to many clients; each client is a ``RosbridgeSession``
fed with the frames it sends (JSON text, or CBOR bytes) and writing its answers through the
async ``send`` it was given. The WebSocket door (``bridges.server``) is a thin adapter, and the
cloud's per-robot relay can feed the same sessions over the robot's own connection.

A graph subscription is shared by every client of a topic; each client gets its own bounded
queue per topic (the oldest message is dropped, and counted, when it is full), so a slow client
only ever loses its own messages and never holds up the robot or another client.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import time
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
    one_by_one,
)
from bridgeos_agent.bridges.graph import BridgeError, BridgeGraph, GraphPublisher, GraphSubscription, Sample
from bridgeos_agent.bridges.rosactions import RosActions
from bridgeos_agent.bridges.rosapi import Rosapi
from bridgeos_agent.bridges.rosbridgewire import (
    COMPRESSIONS,
    LEVELS,
    Fail,
    count_field,
    encode_cbor,
    encode_json,
    fragments,
    name_field,
    text_field,
)

__all__ = ["COMPRESSIONS", "LEVELS", "Rosapi", "Rosbridge", "RosbridgeSession", "encode_cbor", "encode_json"]

logger = logging.getLogger(__name__)

MAX_FRAME_BYTES = 16 << 20  # a frame bigger than this is refused with a status, the connection kept
MAX_QUEUE = 10_000
CONTROL_QUEUE = 1_000  # answers and statuses waiting for a client that does not read
MAX_CALLS_IN_FLIGHT = 64  # service calls one client may have running at once
MAX_FRAGMENTED = 8  # fragmented messages one client may be sending at once
DEFAULT_CALL_TIMEOUT = 30.0
CLIENT_SERVICE_TIMEOUT = 10.0  # how long a ROS caller waits for a client-advertised service to answer


class _Outlet(Outlet):
    """What one client receives of one topic: its subscriptions' options and its queue."""

    __slots__ = ("compression", "fragment_size", "next_at", "options", "throttle_s")

    def __init__(self, topic: str) -> None:
        super().__init__(topic)
        self.options: dict[str, dict[str, Any]] = {}  # subscription id -> its options, in arrival order
        self.compression = "none"
        self.throttle_s = 0.0
        self.fragment_size: int | None = None
        self.next_at = 0.0

    def configure(self, default_queue: int) -> None:
        """Merge the subscriptions as rosbridge does: lowest throttle, longest queue, smallest fragments."""
        options = list(self.options.values())
        self.throttle_s = min(o["throttle_rate"] for o in options) / 1000
        queue_length = max(o["queue_length"] for o in options)
        fragments = [o["fragment_size"] for o in options if o["fragment_size"]]
        self.fragment_size = min(fragments) if fragments else None
        self.compression = options[-1]["compression"]
        # queue_length 0 is rosbridge's "no queueing": with a throttle, only the latest message waits;
        # without one, a short queue still stands between the robot and a slow socket.
        self.resize(queue_length or (1 if self.throttle_s else default_queue))


class Rosbridge:
    """Serve one robot graph to any number of rosbridge v2 clients."""

    def __init__(
        self,
        graph: BridgeGraph,
        *,
        max_frame_bytes: int = MAX_FRAME_BYTES,
        default_queue: int = DEFAULT_QUEUE,
        client_service_timeout: float = CLIENT_SERVICE_TIMEOUT,
        linger_s: float = LINGER_S,
    ) -> None:
        self.graph = graph
        self.max_frame_bytes = max_frame_bytes
        self.default_queue = default_queue
        self.client_service_timeout = client_service_timeout
        self.linger_s = linger_s
        self.sessions: set[RosbridgeSession] = set()
        self.fanouts = Fanouts(graph, linger_s=linger_s)
        self.publishers = Publishers(graph)
        self._services: dict[str, tuple[RosbridgeSession, GraphSubscription]] = {}
        self.rosapi = Rosapi(self)

    def session(self, send: Send, send_many: SendMany | None = None) -> RosbridgeSession:
        """Open a session for a new client whose frames go out through ``send`` (or ``send_many``, several at once)."""
        session = RosbridgeSession(self, send, send_many)
        self.sessions.add(session)
        return session

    async def close(self) -> None:
        """Close every session and leave the graph's topics and services."""
        for session in list(self.sessions):
            await session.close()
        self.fanouts.close()

    # ------------------------------------------------------------------ services

    async def call_service(self, name: str, type_: str | None, args: dict[str, Any], timeout: float) -> dict[str, Any]:
        """Call a service: rosapi's, one a client advertised, or the graph's."""
        if name.startswith("/rosapi/"):
            return await self.rosapi.call(name, args)
        entry = self._services.get(name)
        if entry is not None:
            return await entry[0].serve_call(name, args, timeout)
        return await self.graph.call_service(name, type_, args, timeout)

    async def advertise_service(self, name: str, type_: str, session: RosbridgeSession) -> None:
        """Serve a service in the graph whose calls go to a client."""
        entry = self._services.get(name)
        if entry is not None:
            if entry[0] is session:
                return
            raise Fail(f"{name} is already advertised by another client")
        if name.startswith("/rosapi/"):
            raise Fail(f"{name} is served by the bridge itself")
        if name in await self.graph.services():
            raise Fail(f"{name} is already served in the ROS graph")

        async def handle(args: dict[str, Any]) -> dict[str, Any]:
            return await session.serve_call(name, args, self.client_service_timeout)

        self._services[name] = (session, await self.graph.advertise_service(name, type_, handle))

    def unadvertise_service(self, name: str, session: RosbridgeSession) -> bool:
        """Stop serving a client's service; False when that client did not serve it."""
        entry = self._services.get(name)
        if entry is None or entry[0] is not session:
            return False
        del self._services[name]
        entry[1].close()
        return True

    def subscribed_topics(self) -> list[str]:
        """Return the topics the bridge is subscribed to in the graph."""
        return self.fanouts.topics()

    def client_services(self) -> list[str]:
        """Return the services clients advertise."""
        return list(self._services)

    def forget(self, session: RosbridgeSession) -> None:
        """Drop a closed session."""
        self.sessions.discard(session)


class RosbridgeSession:
    """One rosbridge v2 client: parse its frames, run its operations, queue what goes back to it."""

    def __init__(self, bridge: Rosbridge, send: Send, send_many: SendMany | None = None) -> None:
        self.bridge = bridge
        self.graph = bridge.graph
        self._send = send
        self._send_many = send_many or one_by_one(send)
        self.level = LEVELS["error"]  # rosbridge's default: only errors are reported until set_level
        self._control: deque[str | bytes] = deque()
        self.control_dropped = 0
        self._outlets: dict[str, _Outlet] = {}
        self._order: list[_Outlet] = []
        self._advertised: dict[str, GraphPublisher] = {}
        self._services: set[str] = set()
        self._calls: set[asyncio.Task[None]] = set()
        self._waiting: dict[str, asyncio.Future[dict[str, Any]]] = {}  # our call_service id -> its answer
        self._fragments: dict[str, dict[int, str]] = {}
        self._ids = itertools.count(1)
        self._wake = asyncio.Event()
        self._binary = False  # answer in CBOR once the client speaks CBOR
        self.closed = False
        self.actions = RosActions(self)
        self._handlers: dict[str, Callable[[dict[str, Any]], Awaitable[None]]] = {
            "advertise": self._advertise,
            "unadvertise": self._unadvertise,
            "publish": self._publish,
            "subscribe": self._subscribe,
            "unsubscribe": self._unsubscribe,
            "call_service": self._call_service,
            "service_response": self._service_response,
            "advertise_service": self._advertise_service,
            "unadvertise_service": self._unadvertise_service,
            "set_level": self._set_level,
            "status": self._ignore,
            "fragment": self._fragment,
            **self.actions.handlers(),
        }

    # ------------------------------------------------------------------ frames in

    async def receive(self, data: str | bytes) -> None:
        """Handle one frame from the client; every fault is answered with a status, never raised."""
        if len(data) > self.bridge.max_frame_bytes:
            self.status("error", f"frame of {len(data)} bytes exceeds the limit of {self.bridge.max_frame_bytes}")
            return
        try:
            if isinstance(data, str):
                message = json.loads(data)
            else:
                import cbor2

                message = cbor2.loads(data)
                self._binary = True
        except (ValueError, UnicodeDecodeError, EOFError) as exc:
            kind = "JSON" if isinstance(data, str) else "CBOR"
            self.status("error", f"malformed {kind}: {exc}")
            return
        except Exception as exc:  # cbor2 raises its own decode errors for any bad byte
            self.status("error", f"malformed CBOR: {exc}")
            return
        if not isinstance(message, dict) or not isinstance(message.get("op"), str):
            self.status("error", "a rosbridge message must be an object with an 'op' string")
            return
        op, ident = message["op"], message.get("id")
        if ident is not None and not isinstance(ident, str | int):
            ident = None
        handler = self._handlers.get(op)
        if handler is None:
            self.status("error", f"unknown op {op[:64]!r}", ident)
            return
        try:
            await handler(message)
        except Fail as exc:
            self.status(exc.level, f"{op}: {exc}", ident)
        except BridgeError as exc:
            self.status("error", f"{op}: {exc}", ident)
        except Exception as exc:  # a fault of ours must cost the client one answer, not its connection
            logger.exception("rosbridge: %s failed", op)
            self.status("error", f"{op}: internal error: {type(exc).__name__}: {exc}"[:500], ident)

    async def _ignore(self, message: dict[str, Any]) -> None:
        return

    async def _fragment(self, message: dict[str, Any]) -> None:
        ident, data, num, total = (message.get(k) for k in ("id", "data", "num", "total"))
        if not isinstance(ident, str | int) or not isinstance(data, str):
            raise Fail("a fragment needs an 'id' and a 'data' string")
        if not isinstance(num, int) or not isinstance(total, int) or not 0 <= num < total <= 100_000:
            raise Fail("a fragment needs 0 <= num < total")
        key = str(ident)
        parts = self._fragments.get(key)
        if parts is None:
            if len(self._fragments) >= MAX_FRAGMENTED:
                raise Fail(f"more than {MAX_FRAGMENTED} fragmented messages at once")
            parts = self._fragments[key] = {}
        parts[num] = data
        if sum(len(part) for part in parts.values()) > self.bridge.max_frame_bytes:
            del self._fragments[key]
            raise Fail(f"fragmented message {key} exceeds {self.bridge.max_frame_bytes} bytes")
        if len(parts) == total:
            del self._fragments[key]
            await self.receive("".join(parts[i] for i in range(total)))

    async def _set_level(self, message: dict[str, Any]) -> None:
        level = message.get("level")
        if level not in LEVELS:
            raise Fail(f"level must be one of {', '.join(LEVELS)}, not {level!r}")
        self.level = LEVELS[level]

    async def _advertise(self, message: dict[str, Any]) -> None:
        topic, type_ = name_field(message, "topic"), text_field(message, "type")
        assert type_ is not None
        publisher = self._advertised.get(topic)
        if publisher is not None:
            if self.graph.normalize_type(type_) != publisher.type:
                raise Fail(f"{topic} is advertised with type {publisher.type}, not {type_}")
            return
        self._advertised[topic] = await self.bridge.publishers.advertise(topic, type_, self)

    async def _unadvertise(self, message: dict[str, Any]) -> None:
        topic = name_field(message, "topic")
        if self._advertised.pop(topic, None) is None:
            raise Fail(f"{topic} is not advertised by this client", "warning")
        self.bridge.publishers.unadvertise(topic, self)

    async def _publish(self, message: dict[str, Any]) -> None:
        topic = name_field(message, "topic")
        msg = message.get("msg", {})
        if not isinstance(msg, dict):
            raise Fail("'msg' must be an object")
        publisher = self._advertised.get(topic)
        if publisher is None:
            # rosbridge publishes on an existing topic without an advertise, with the topic's type.
            known = (await self.graph.topics()).get(topic)
            if known is None:
                raise Fail(f"{topic} does not exist: advertise it with a type first")
            publisher = self._advertised[topic] = await self.bridge.publishers.advertise(topic, known, self)
        publisher.publish(msg)

    async def _subscribe(self, message: dict[str, Any]) -> None:
        topic = name_field(message, "topic")
        type_ = text_field(message, "type", required=False)
        compression = message.get("compression") or "none"
        if compression not in COMPRESSIONS:
            raise Fail(f"compression {compression!r} is not supported: use one of {', '.join(COMPRESSIONS)}")
        options = {
            "throttle_rate": count_field(message, "throttle_rate", 0, upto=3_600_000),
            "queue_length": count_field(message, "queue_length", 0, upto=MAX_QUEUE),
            "fragment_size": count_field(message, "fragment_size", 0) or None,
            "compression": compression,
        }
        if options["fragment_size"] is not None and compression != "none":
            raise Fail("fragment_size applies to JSON only (compression 'none')")
        ident = message.get("id")
        key = str(ident) if isinstance(ident, str | int) else f"subscribe:{topic}"
        outlet = self._outlets.get(topic)
        if outlet is None:
            outlet = _Outlet(topic)
            await self.bridge.fanouts.attach(topic, type_, outlet, self)
            self._outlets[topic] = outlet
            self._order.append(outlet)
        elif type_ is not None and self.graph.normalize_type(type_) != outlet.type:
            raise Fail(f"{topic} is of type {outlet.type}, not {type_}")
        outlet.options.pop(key, None)
        outlet.options[key] = options
        outlet.configure(self.bridge.default_queue)

    async def _unsubscribe(self, message: dict[str, Any]) -> None:
        topic = name_field(message, "topic")
        outlet = self._outlets.get(topic)
        if outlet is None:
            raise Fail(f"not subscribed to {topic}", "warning")
        ident = message.get("id")
        if isinstance(ident, str | int) and str(ident) in outlet.options:
            del outlet.options[str(ident)]
        else:
            outlet.options.clear()
        if outlet.options:
            outlet.configure(self.bridge.default_queue)
        else:
            self._drop_outlet(outlet)

    def _drop_outlet(self, outlet: _Outlet) -> None:
        self._outlets.pop(outlet.topic, None)
        with contextlib.suppress(ValueError):
            self._order.remove(outlet)
        self.bridge.fanouts.detach(outlet.topic, outlet)

    async def _call_service(self, message: dict[str, Any]) -> None:
        name = name_field(message, "service")
        type_ = text_field(message, "type", required=False)
        args = message.get("args", {})
        if isinstance(args, list) and not args:
            args = {}
        if not isinstance(args, dict):
            raise Fail("'args' must be an object with the request's fields")
        timeout = message.get("timeout") or DEFAULT_CALL_TIMEOUT
        if isinstance(timeout, bool) or not isinstance(timeout, int | float) or not 0 < timeout <= 3600:
            raise Fail(f"'timeout' must be a number of seconds in (0, 3600], not {timeout!r}")
        if len(self._calls) >= MAX_CALLS_IN_FLIGHT:
            raise Fail(f"{MAX_CALLS_IN_FLIGHT} service calls are already running for this client")
        task = asyncio.get_running_loop().create_task(self._run_call(name, type_, args, float(timeout), message))
        self._calls.add(task)
        task.add_done_callback(self._calls.discard)

    async def _run_call(
        self, name: str, type_: str | None, args: dict[str, Any], timeout: float, message: dict[str, Any]
    ) -> None:
        answer: dict[str, Any] = {"op": "service_response", "service": message["service"]}
        if "id" in message:
            answer["id"] = message["id"]
        try:
            values = await asyncio.wait_for(self.bridge.call_service(name, type_, args, timeout), timeout)
        except BridgeError as exc:
            answer.update(values=str(exc), result=False)
        except TimeoutError:
            answer.update(values=f"{name} did not answer within {timeout:g} s", result=False)
        else:
            answer.update(values=values, result=True)
        self.send(answer)

    async def _service_response(self, message: dict[str, Any]) -> None:
        ident = message.get("id")
        future = self._waiting.pop(str(ident), None) if isinstance(ident, str | int) else None
        if future is None:
            raise Fail(f"no call is waiting for a response with id {ident!r}")
        if future.done():
            return
        values = message.get("values", {})
        if message.get("result", True) is False:
            future.set_exception(BridgeError(f"the client's service failed: {values}"))
        elif not isinstance(values, dict):
            future.set_exception(BridgeError("the client answered with 'values' that are not an object"))
        else:
            future.set_result(values)

    async def _advertise_service(self, message: dict[str, Any]) -> None:
        name, type_ = name_field(message, "service"), text_field(message, "type")
        assert type_ is not None
        await self.bridge.advertise_service(name, type_, self)
        self._services.add(name)

    async def _unadvertise_service(self, message: dict[str, Any]) -> None:
        name = name_field(message, "service")
        if not self.bridge.unadvertise_service(name, self):
            raise Fail(f"{name} is not advertised by this client", "warning")
        self._services.discard(name)

    async def serve_call(self, name: str, args: dict[str, Any], timeout: float) -> dict[str, Any]:
        """Pass a ROS call of a service this client advertised on to it and wait for its answer."""
        if self.closed:
            raise BridgeError(f"the client serving {name} has gone")
        ident = f"service_request:{name}:{next(self._ids)}"
        future: asyncio.Future[dict[str, Any]] = asyncio.get_running_loop().create_future()
        self._waiting[ident] = future
        self.send({"op": "call_service", "id": ident, "service": name, "args": args})
        try:
            return await asyncio.wait_for(future, timeout)
        except TimeoutError:
            raise BridgeError(f"the client serving {name} did not answer within {timeout:g} s") from None
        finally:
            self._waiting.pop(ident, None)

    # ------------------------------------------------------------------ frames out

    def status(self, level: str, text: str, ident: Any = None) -> None:
        """Tell the client something at a level, if its level asks for it."""
        if LEVELS[level] < self.level:
            return
        message: dict[str, Any] = {"op": "status", "level": level, "msg": text}
        if ident is not None:
            message["id"] = ident
        self.send(message)

    def send(self, message: dict[str, Any], *, compression: str = "none", fragment_size: int | None = None) -> None:
        """Queue a protocol message (not a topic's) for the client, in CBOR if it asked, in fragments if too long."""
        if self.closed:
            return
        frame = encode_cbor(message) if self._binary or compression == "cbor" else encode_json(message)
        pieces = [frame]
        if fragment_size and isinstance(frame, str) and len(frame) > fragment_size:
            pieces = list(fragments(frame, fragment_size, f"{message['op']}:{next(self._ids)}"))
        for piece in pieces:
            if len(self._control) >= CONTROL_QUEUE:
                self._control.popleft()
                self.control_dropped += 1
            self._control.append(piece)
        self._wake.set()

    def wake(self) -> None:
        """Tell the writer there is something to send."""
        self._wake.set()

    def stats(self) -> dict[str, dict[str, int]]:
        """Return each topic's messages sent and dropped for this client."""
        return {o.topic: {"sent": o.sent, "dropped": o.dropped, "queued": len(o.queue)} for o in self._order}

    async def run(self) -> None:
        """Write queued frames to the client until the session closes (the door runs this beside its reader)."""
        while not self.closed:
            frames, delay = self._take()
            if frames:
                # Everything ready goes in one go: a door writes a batch to its socket at once.
                while len(frames) < BATCH_FRAMES:
                    more, _ = self._take()
                    if not more:
                        break
                    frames += more
                await self._send_many(frames)
                continue
            self._wake.clear()
            if delay is None:
                await self._wake.wait()
            else:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self._wake.wait(), delay)

    def _take(self) -> tuple[list[str | bytes], float | None]:
        """Return the next frames to send, or how long until a throttled topic may send (None: wait)."""
        if self._control:
            return [self._control.popleft()], None
        now = time.monotonic()
        delay: float | None = None
        order = self._order
        for index, outlet in enumerate(order):
            if not outlet.queue:
                continue
            if outlet.next_at > now:
                wait = outlet.next_at - now
                delay = wait if delay is None else min(delay, wait)
                continue
            sample = outlet.queue.popleft()
            outlet.next_at = now + outlet.throttle_s
            # Round robin: the topic just served goes last, so a busy topic cannot starve the others.
            order.append(order.pop(index))
            try:
                frames = self._encode(outlet, sample)
            except Exception as exc:  # a message the converter cannot read must not stop the writer
                logger.exception("rosbridge: cannot encode a message of %s", outlet.topic)
                self.status("error", f"cannot convert a message of {outlet.topic}: {exc}")
                return [], 0.0
            outlet.sent += 1
            return frames, None
        return [], delay

    def _encode(self, outlet: _Outlet, sample: Sample) -> list[str | bytes]:
        key = (outlet.topic, outlet.compression)
        frame = sample.frames.get(key)
        if frame is None:
            if outlet.compression == "cbor-raw":
                secs, nsecs = sample.stamp
                raw = {"secs": secs, "nsecs": nsecs, "bytes": bytes(sample.raw)}
                frame = encode_cbor({"op": "publish", "topic": outlet.topic, "msg": raw})
            elif outlet.compression == "cbor":
                frame = encode_cbor({"op": "publish", "topic": outlet.topic, "msg": sample.msg()})
            else:
                frame = encode_json({"op": "publish", "topic": outlet.topic, "msg": sample.msg()})
            sample.frames[key] = frame
        size = outlet.fragment_size
        if size is None or not isinstance(frame, str) or len(frame) <= size:
            return [frame]
        return list(fragments(frame, size, f"{outlet.topic}:{outlet.sent}"))

    # ------------------------------------------------------------------ end

    async def close(self) -> None:
        """Undo everything the client did in the graph and fail what waits on it."""
        if self.closed:
            return
        self.closed = True
        self._wake.set()
        for outlet in list(self._outlets.values()):
            self._drop_outlet(outlet)
        for topic in list(self._advertised):
            self.bridge.publishers.unadvertise(topic, self)
        self._advertised.clear()
        for name in list(self._services):
            self.bridge.unadvertise_service(name, self)
        for future in self._waiting.values():
            if not future.done():
                future.set_exception(BridgeError("the client went away"))
        self._waiting.clear()
        for task in list(self._calls):
            task.cancel()
        await asyncio.gather(*self._calls, return_exceptions=True)
        await self.actions.close()
        self.bridge.forget(self)
