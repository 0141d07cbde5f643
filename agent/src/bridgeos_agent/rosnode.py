"""A ROS 1 node on asyncio: master and slave XML-RPC, TCPROS topics and services, bytes unparsed.

The Skill Router speaks ROS itself instead of importing rospy: rospy allows one node per
process, costs ~35 MB and cannot be imported by the agent's own interpreter. This node
does what a router needs and no more: it registers publications, subscriptions and
services with the master (batched in ``system.multicall`` requests), answers the slave API
(``requestTopic``, ``publisherUpdate``, ``getBusInfo``, ``getPid``...), accepts TCPROS
subscribers and service clients, connects to publishers, and hands each burst of message
frames on as one ``bytes`` without decoding a message.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import socket
import xmlrpc.client
from collections import deque
from collections.abc import Awaitable, Callable, Iterable
from typing import Any
from urllib.parse import urlsplit

import aiohttp
from aiohttp import web

from bridgeos_agent.tcpros import HeaderError, decode_header, encode_header, split_frames

__all__ = [
    "Inbound",
    "MasterError",
    "Outbound",
    "Publication",
    "RosNode",
    "Subscription",
    "iter_frames",
    "read_header",
]

logger = logging.getLogger(__name__)

BATCH = 500  # master calls per system.multicall request
QUEUE_MESSAGES = 1000  # per subscriber connection, once its socket stops taking data...
QUEUE_BYTES = 16 << 20  # ...and at most this much of it (a thousand pointclouds would not fit a robot)
HIGH_WATER = 1 << 20  # bytes the kernel-side write buffer may hold before a connection queues
# A publisher whose bursts arrive closer than this is read in bursts of COALESCE_S instead: one
# wakeup per message would cost the router several µs of CPU each (throughput under load beats a
# fraction of a millisecond there; at nominal rates nothing waits).
COALESCE_GAP_S = 0.0002
COALESCE_S = 0.0005

ServiceHandler = Callable[[dict[str, str], asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]
MessageCallback = Callable[["Subscription", bytes, int, "Inbound"], None]


class MasterError(RuntimeError):
    """The ROS master refused a call or could not be reached."""


def iter_frames(blob: bytes) -> Iterable[bytes]:
    """Yield each whole frame (length prefix included) of a burst of frames."""
    offset, end = 0, len(blob)
    while offset < end:
        size = int.from_bytes(blob[offset : offset + 4], "little")
        yield blob[offset : offset + 4 + size]
        offset += 4 + size


async def read_header(reader: asyncio.StreamReader) -> dict[str, str]:
    """Read one TCPROS connection header from a stream."""
    size = int.from_bytes(await reader.readexactly(4), "little")
    if size > 1 << 20:
        raise HeaderError(f"connection header of {size} bytes")
    return decode_header(await reader.readexactly(size))


def _nodelay(transport: asyncio.BaseTransport) -> None:
    sock = transport.get_extra_info("socket")
    if sock is not None and sock.family in (socket.AF_INET, socket.AF_INET6):
        with contextlib.suppress(OSError):
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


class Outbound:
    """One subscriber connected to a publication: a bounded queue once its socket backs up."""

    __slots__ = (
        "_flusher",
        "backlog",
        "backlog_bytes",
        "callerid",
        "closed",
        "dropped",
        "publication",
        "transport",
        "writer",
    )

    def __init__(self, publication: Publication, writer: asyncio.StreamWriter, callerid: str) -> None:
        self.publication = publication
        self.writer = writer
        self.transport = writer.transport
        self.callerid = callerid
        self.backlog: deque[bytes] | None = None
        self.backlog_bytes = 0
        self.dropped = 0
        self.closed = False
        self._flusher: asyncio.Task | None = None

    def send(self, blob: bytes, count: int) -> int:
        """Write a burst with one write, or queue it while the peer is slow; return messages dropped."""
        if self.closed:
            return 0
        if self.backlog is None:
            if self.transport.get_write_buffer_size() <= HIGH_WATER:
                self.transport.write(blob)
                return 0
            self.backlog = deque()
            self._flusher = asyncio.get_running_loop().create_task(self._flush())
        backlog = self.backlog
        backlog.extend(iter_frames(blob) if count != 1 else (blob,))
        self.backlog_bytes += len(blob)
        # A stalled subscriber loses its own oldest messages; nobody else waits for it.
        overflow = 0
        while len(backlog) > QUEUE_MESSAGES or (self.backlog_bytes > QUEUE_BYTES and len(backlog) > 1):
            self.backlog_bytes -= len(backlog.popleft())
            overflow += 1
        self.dropped += overflow
        return overflow

    async def _flush(self) -> None:
        try:
            while self.backlog:
                await self.writer.drain()
                data = b"".join(self.backlog)
                self.backlog.clear()
                self.backlog_bytes = 0
                self.transport.write(data)
                await self.writer.drain()
        except (ConnectionError, RuntimeError):
            self.close()
        finally:
            self.backlog = None
            self.backlog_bytes = 0
            self._flusher = None

    def close(self) -> None:
        """Close the connection and forget it."""
        if not self.closed:
            self.closed = True
            self.transport.close()
            with contextlib.suppress(ValueError):
                self.publication.connections.remove(self)  # type: ignore[union-attr]


class Publication:
    """A topic the node publishes; message bytes are forwarded as given."""

    __slots__ = ("connections", "definition", "md5sum", "name", "on_connect", "type")

    def __init__(self, name: str, type_: str) -> None:
        self.name = name
        self.type = type_
        self.md5sum = "*"  # unknown until a publisher upstream (or a subscriber) tells
        self.definition = ""
        # Kept small for routers of thousands of topics: a list only once someone subscribes.
        self.connections: list[Outbound] | tuple[()] = ()
        self.on_connect: Callable[[Outbound], None] | None = None

    def send(self, blob: bytes, count: int) -> int:
        """Send a burst of frames to every subscriber; return the messages dropped."""
        dropped = 0
        for connection in self.connections:
            dropped += connection.send(blob, count)
        return dropped

    def reply_header(self, request: dict[str, str], callerid: str) -> dict[str, str]:
        """Return the header answering a subscriber, echoing its type while ours is unknown."""
        wanted = request.get("md5sum", "*")
        if self.md5sum != "*" and wanted not in ("*", self.md5sum):
            return {"error": f"{self.name}: md5sum {wanted} does not match {self.type}'s {self.md5sum}"}
        if self.md5sum == "*" and wanted != "*":
            return {
                "callerid": callerid,
                "md5sum": wanted,
                "type": request.get("type", self.type),
                "message_definition": request.get("message_definition", ""),
                "latching": "0",
                "topic": self.name,
            }
        return {
            "callerid": callerid,
            "md5sum": self.md5sum,
            "type": self.type,
            "message_definition": self.definition,
            "latching": "0",
            "topic": self.name,
        }


class Inbound(asyncio.Protocol):
    """A TCPROS connection to one publisher: hands each burst of whole frames on at once."""

    def __init__(self, subscription: Subscription, publisher: str) -> None:
        self.subscription = subscription
        self.publisher = publisher
        self.header: dict[str, str] | None = None
        self.transport: asyncio.Transport | None = None
        self._buffer = bytearray()
        self._last = 0.0
        self._loop = asyncio.get_running_loop()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        _nodelay(transport)
        sub = self.subscription
        transport.write(  # type: ignore[attr-defined]
            encode_header(
                {
                    "callerid": sub.node.name,
                    "topic": sub.name,
                    "md5sum": "*",
                    "type": "*",
                    "message_definition": "",
                    "tcp_nodelay": "1",
                }
            )
        )

    def data_received(self, data: bytes) -> None:
        now = self._loop.time()
        if now - self._last < COALESCE_GAP_S and self.header is not None:
            self.transport.pause_reading()
            self._loop.call_later(COALESCE_S, self._resume)
        self._last = now
        buffer = self._buffer
        if self.header is None:
            buffer += data
            if len(buffer) < 4:
                return
            size = int.from_bytes(buffer[:4], "little")
            if len(buffer) < 4 + size:
                return
            try:
                header = decode_header(bytes(buffer[4 : 4 + size]))
            except HeaderError as exc:
                logger.warning("%s: bad header from %s: %s", self.subscription.name, self.publisher, exc)
                self.transport.close()
                return
            del buffer[: 4 + size]
            if "error" in header:
                logger.warning("%s: %s refused: %s", self.subscription.name, self.publisher, header["error"])
                self.transport.close()
                return
            self.header = header
            self.subscription.on_header(self)
            if not buffer:
                return
            data = bytes(buffer)
            buffer.clear()
        elif buffer:
            buffer += data
            data = bytes(buffer)
            buffer.clear()
        try:
            end, count = split_frames(data)
        except HeaderError as exc:
            logger.warning("%s: %s", self.subscription.name, exc)
            self.transport.close()
            return
        if end < len(data):
            buffer += data[end:]
            data = data[:end]
        if count:
            self.subscription.callback(self.subscription, data, count, self)

    def _resume(self) -> None:
        if self.transport is not None and not self.transport.is_closing():
            self.transport.resume_reading()

    def connection_lost(self, exc: Exception | None) -> None:
        self.subscription.on_lost(self)


_NO_CONNECTIONS: dict[str, Any] = {}  # shared, never written: every write replaces it first


class Subscription:
    """A topic the node subscribes to, whatever its type (md5sum ``*``, like AnyMsg)."""

    __slots__ = ("callback", "connections", "name", "node", "owner", "type", "where")

    def __init__(self, node: RosNode, name: str, type_: str, callback: MessageCallback) -> None:
        self.node = node
        self.name = name
        self.type = type_
        self.callback = callback
        self.owner: Any = None  # whatever the node's user keeps here (the router: its topic)
        self.where: str | None = None
        # publisher API -> connection (None while connecting); a dict only once there are publishers
        self.connections: dict[str, Inbound | None] = _NO_CONNECTIONS

    @property
    def connected(self) -> bool:
        """Tell whether at least one publisher's connection is up."""
        return any(c is not None and c.header is not None for c in self.connections.values())

    def update(self, publishers: Iterable[str], *, complete: bool) -> None:
        """Connect to new publishers; with ``complete``, drop those no longer listed."""
        wanted = {uri for uri in publishers if uri != self.node.uri}
        if wanted and self.connections is _NO_CONNECTIONS:
            self.connections = {}
        for uri in wanted - self.connections.keys():
            self.connections[uri] = None
            self.node.spawn(self.node.connect(self, uri))
        if complete:
            for uri in set(self.connections) - wanted:
                connection = self.connections.pop(uri)
                if connection is not None and connection.transport is not None:
                    connection.transport.close()

    def on_header(self, inbound: Inbound) -> None:
        """Take the publisher's type, md5sum and definition for whoever forwards this topic."""
        self.node.on_publisher_header(self, inbound)

    def on_lost(self, inbound: Inbound) -> None:
        """Forget a closed publisher connection."""
        if self.connections.get(inbound.publisher) is inbound:
            del self.connections[inbound.publisher]

    def close(self) -> None:
        """Close every publisher connection."""
        for connection in self.connections.values():
            if connection is not None and connection.transport is not None:
                connection.transport.close()
        self.connections = _NO_CONNECTIONS


class RosNode:
    """One ROS 1 node on the running event loop, with batched master registrations."""

    def __init__(
        self,
        name: str,
        master_uri: str,
        *,
        host: str = "127.0.0.1",
        on_publisher_header: Callable[[Subscription, Inbound], None] | None = None,
    ) -> None:
        self.name = name
        self.master_uri = master_uri
        self.host = host
        self.uri = ""
        self.tcpros_port = 0
        self.publications: dict[str, Publication] = {}
        self.subscriptions: dict[str, Subscription] = {}
        self.services: dict[str, ServiceHandler] = {}
        self._header_hook = on_publisher_header
        self._session: aiohttp.ClientSession | None = None
        self._runner: web.AppRunner | None = None
        self._server: asyncio.Server | None = None
        self._pending: list[tuple[str, tuple[Any, ...]]] = []
        self._errors: list[MasterError] = []
        self._wake = asyncio.Event()
        self._idle = asyncio.Event()
        self._idle.set()
        self._tasks: set[asyncio.Task] = set()
        self._registrar: asyncio.Task | None = None
        self._ids = itertools.count(1)

    # ------------------------------------------------------------------ life cycle

    async def start(self) -> None:
        """Serve the slave API and TCPROS, and check the master answers."""
        bind = "127.0.0.1" if self.host in ("127.0.0.1", "localhost", "::1") else None
        self._session = aiohttp.ClientSession(
            connector=aiohttp.TCPConnector(limit=64), timeout=aiohttp.ClientTimeout(total=30)
        )
        try:
            # A master that is not there should cost a Skill seconds, not the 30 s of a registration.
            await asyncio.wait_for(self.master_call("getPid"), 5)
            app = web.Application(client_max_size=16 << 20)
            app.router.add_post("/{tail:.*}", self._slave_request)
            # A master keeps its slave connections alive: do not wait for it to hang up on close.
            self._runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)
            await self._runner.setup()
            site = web.TCPSite(self._runner, bind, 0)
            await site.start()
            port = self._runner.addresses[0][1]
            self.uri = f"http://{self.host}:{port}/"
            self._server = await asyncio.start_server(self._accept, bind, 0)
            self.tcpros_port = self._server.sockets[0].getsockname()[1]
        except BaseException:
            await self.close(unregister=False)
            raise
        self._registrar = asyncio.get_running_loop().create_task(self._register_loop())

    async def close(self, *, unregister: bool = True) -> None:
        """Unregister from the master and close every server and connection."""
        if unregister and self.uri:
            calls = [("unregisterPublisher", (name, self.uri)) for name in self.publications]
            calls += [("unregisterSubscriber", (name, self.uri)) for name in self.subscriptions]
            rosrpc = f"rosrpc://{self.host}:{self.tcpros_port}"
            calls += [("unregisterService", (name, rosrpc)) for name in self.services]
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._multicall(calls), 10)
        if self._registrar is not None:
            self._registrar.cancel()
            await asyncio.gather(self._registrar, return_exceptions=True)
        self._pending.clear()
        self._idle.set()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for subscription in self.subscriptions.values():
            subscription.close()
        for publication in self.publications.values():
            for connection in list(publication.connections):
                connection.close()
        if self._server is not None:
            self._server.close()
            self._server = None
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._session is not None:
            await self._session.close()
            self._session = None

    def spawn(self, coroutine: Awaitable[Any]) -> None:
        """Run a coroutine the node owns (cancelled when it closes)."""
        task = asyncio.get_running_loop().create_task(coroutine)  # type: ignore[arg-type]
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # ------------------------------------------------------------------ master calls

    async def _xmlrpc(self, uri: str, method: str, params: tuple[Any, ...]) -> Any:
        if self._session is None:
            raise MasterError("the node is not started")
        body = xmlrpc.client.dumps(params, method, allow_none=False)
        async with self._session.post(uri, data=body, headers={"Content-Type": "text/xml"}) as response:
            text = await response.read()
        (result,), _ = xmlrpc.client.loads(text)
        return result

    async def master_call(self, method: str, *params: Any) -> Any:
        """Call the master; return the value of a successful (code 1) answer."""
        try:
            code, message, value = await self._xmlrpc(self.master_uri, method, (self.name, *params))
        except (aiohttp.ClientError, OSError, TimeoutError, xmlrpc.client.Error, ValueError) as exc:
            raise MasterError(f"ROS master {self.master_uri} did not answer {method}: {exc}") from None
        if code != 1:
            raise MasterError(f"ROS master refused {method}{params}: {message}")
        return value

    async def _multicall(self, calls: list[tuple[str, tuple[Any, ...]]]) -> list[Any]:
        """Make many master calls in as few requests as possible; failures come back as exceptions."""
        results: list[Any] = []
        for start in range(0, len(calls), BATCH):
            chunk = calls[start : start + BATCH]
            request = [{"methodName": m, "params": [self.name, *p]} for m, p in chunk]
            try:
                answers = await self._xmlrpc(self.master_uri, "system.multicall", (request,))
            except (aiohttp.ClientError, OSError, TimeoutError, xmlrpc.client.Error, ValueError) as exc:
                error = MasterError(f"ROS master {self.master_uri} did not answer: {exc}")
                results.extend(error for _ in chunk)
                continue
            for (method, params), answer in zip(chunk, answers, strict=True):
                if isinstance(answer, dict) or answer[0][0] != 1:
                    text = answer.get("faultString") if isinstance(answer, dict) else answer[0][1]
                    results.append(MasterError(f"ROS master refused {method} {params[0]}: {text}"))
                else:
                    results.append(answer[0][2])
        return results

    def _enqueue(self, method: str, *params: Any) -> None:
        self._pending.append((method, params))
        self._idle.clear()
        self._wake.set()

    async def _register_loop(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._pending:
                # Publishers first, so subscribers find them in their answer and nobody is notified twice.
                batch = sorted(self._pending[: BATCH * 4], key=lambda call: call[0] != "registerPublisher")
                del self._pending[: BATCH * 4]
                results = await self._multicall(batch)
                for (method, params), result in zip(batch, results, strict=True):
                    if isinstance(result, MasterError):
                        self._errors.append(result)
                    elif method == "registerSubscriber":
                        subscription = self.subscriptions.get(params[0])
                        if subscription is not None:
                            subscription.update(result, complete=False)
                batch = results = []  # nothing of a finished batch outlives it
            self._idle.set()

    async def settle(self) -> list[MasterError]:
        """Wait until every registration queued so far was sent; return (and forget) those refused."""
        await self._idle.wait()
        errors, self._errors = self._errors, []
        return errors

    # ------------------------------------------------------------------ topics and services

    def advertise(self, name: str, type_: str) -> Publication:
        """Publish a topic; the registration goes with the next batch (``settle`` waits for it)."""
        publication = self.publications.get(name)
        if publication is None:
            publication = self.publications[name] = Publication(name, type_)
        self._enqueue("registerPublisher", name, type_, self.uri)
        return publication

    def unadvertise(self, name: str) -> None:
        """Stop publishing a topic and close its subscribers' connections."""
        publication = self.publications.pop(name, None)
        if publication is not None:
            for connection in list(publication.connections):
                connection.close()
            self._enqueue("unregisterPublisher", name, self.uri)

    def subscribe(self, name: str, type_: str, callback: MessageCallback) -> Subscription:
        """Subscribe to a topic; the registration goes with the next batch (``settle`` waits for it)."""
        subscription = self.subscriptions.get(name)
        if subscription is None:
            subscription = self.subscriptions[name] = Subscription(self, name, type_, callback)
        self._enqueue("registerSubscriber", name, type_, self.uri)
        return subscription

    def unsubscribe(self, name: str) -> None:
        """Stop subscribing to a topic."""
        subscription = self.subscriptions.pop(name, None)
        if subscription is not None:
            subscription.close()
            self._enqueue("unregisterSubscriber", name, self.uri)

    def advertise_service(self, name: str, handler: ServiceHandler) -> None:
        """Serve a service; each client connection is handed to ``handler`` after its header."""
        self.services[name] = handler
        self._enqueue("registerService", name, f"rosrpc://{self.host}:{self.tcpros_port}", self.uri)

    def unadvertise_service(self, name: str) -> None:
        """Stop serving a service."""
        if self.services.pop(name, None) is not None:
            self._enqueue("unregisterService", name, f"rosrpc://{self.host}:{self.tcpros_port}")

    async def lookup_service(self, name: str) -> tuple[str, int] | None:
        """Return where a service is served, or None when nobody serves it."""
        try:
            uri = await self.master_call("lookupService", name)
        except MasterError:
            return None
        parts = urlsplit(uri)
        if parts.scheme != "rosrpc" or not parts.hostname or not parts.port:
            return None
        return parts.hostname, parts.port

    def on_publisher_header(self, subscription: Subscription, inbound: Inbound) -> None:
        """Pass a publisher's connection header to whoever owns the node."""
        if self._header_hook is not None:
            self._header_hook(subscription, inbound)

    async def connect(self, subscription: Subscription, publisher: str) -> None:
        """Ask a publisher for a TCPROS connection and open it."""
        try:
            code, message, protocol = await self._xmlrpc(
                publisher, "requestTopic", (self.name, subscription.name, [["TCPROS"]])
            )
            if code != 1 or not protocol or protocol[0] != "TCPROS":
                raise MasterError(message or "no TCPROS")
            _, host, port = protocol
            await asyncio.get_running_loop().create_connection(
                lambda: self._inbound(subscription, publisher), host, int(port)
            )
        except (aiohttp.ClientError, OSError, TimeoutError, xmlrpc.client.Error, ValueError, MasterError) as exc:
            logger.info("%s: cannot connect to publisher %s: %s", subscription.name, publisher, exc)
            if subscription.connections.get(publisher) is None:
                subscription.connections.pop(publisher, None)

    def _inbound(self, subscription: Subscription, publisher: str) -> Inbound:
        inbound = Inbound(subscription, publisher)
        if publisher in subscription.connections and self.subscriptions.get(subscription.name) is subscription:
            subscription.connections[publisher] = inbound
        return inbound

    # ------------------------------------------------------------------ TCPROS server

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        _nodelay(writer.transport)
        try:
            header = await asyncio.wait_for(read_header(reader), 30)
        except (asyncio.IncompleteReadError, HeaderError, TimeoutError, ConnectionError):
            writer.close()
            return
        if "service" in header:
            handler = self.services.get(header["service"])
            if handler is None:
                writer.write(encode_header({"error": f"{self.name} does not serve {header['service']}"}))
                writer.close()
                return
            try:
                await handler(header, reader, writer)
            finally:
                writer.close()
            return
        publication = self.publications.get(header.get("topic", ""))
        if publication is None:
            writer.write(encode_header({"error": f"{self.name} does not publish {header.get('topic')}"}))
            writer.close()
            return
        reply = publication.reply_header(header, self.name)
        writer.write(encode_header(reply))
        if "error" in reply:
            writer.close()
            return
        outbound = Outbound(publication, writer, header.get("callerid", ""))
        if not publication.connections:
            publication.connections = []
        publication.connections.append(outbound)  # type: ignore[union-attr]
        if publication.on_connect is not None:
            publication.on_connect(outbound)
        try:
            while await reader.read(4096):  # subscribers send nothing after their header
                pass
        except ConnectionError:
            pass
        finally:
            outbound.close()

    # ------------------------------------------------------------------ slave API

    async def _slave_request(self, request: web.Request) -> web.Response:
        try:
            params, method = xmlrpc.client.loads(await request.read())
            result = self._slave_call(method or "", params)
            body = xmlrpc.client.dumps((result,), methodresponse=True, allow_none=False)
        except Exception as exc:  # a peer's bad call is answered, never raised into the server
            body = xmlrpc.client.dumps(xmlrpc.client.Fault(1, str(exc)), methodresponse=True)
        return web.Response(body=body.encode(), content_type="text/xml")

    def _slave_call(self, method: str, params: tuple[Any, ...]) -> Any:
        if method == "requestTopic":
            _, topic, protocols = params
            if topic not in self.publications:
                return [0, f"{self.name} does not publish {topic}", []]
            if not any(p and p[0] == "TCPROS" for p in protocols):
                return [0, "only TCPROS is supported", []]
            return [1, "ready on TCPROS", ["TCPROS", self.host, self.tcpros_port]]
        if method == "publisherUpdate":
            _, topic, publishers = params
            subscription = self.subscriptions.get(topic)
            if subscription is not None:
                subscription.update(publishers, complete=True)
            return [1, "", 0]
        if method == "getPid":
            return [1, "", os.getpid()]
        if method == "getMasterUri":
            return [1, "", self.master_uri]
        if method == "getPublications":
            return [1, "", [[p.name, p.type] for p in self.publications.values()]]
        if method == "getSubscriptions":
            return [1, "", [[s.name, s.type] for s in self.subscriptions.values()]]
        if method == "getBusStats":
            return [1, "", [[], [], []]]
        if method == "getBusInfo":
            return [1, "", self._bus_info()]
        if method == "paramUpdate":
            return [1, "", 0]
        if method == "shutdown":
            # The router belongs to its Skill, not to whoever runs `rosnode kill`.
            logger.warning("%s: ignoring a shutdown request: %s", self.name, params[1:] or "")
            return [1, "the Skill Router stops with its Skill", 0]
        raise ValueError(f"unknown method {method!r}")

    def _bus_info(self) -> list[list[Any]]:
        info: list[list[Any]] = []
        for publication in self.publications.values():
            for connection in publication.connections:
                info.append([next(self._ids), connection.callerid, "o", "TCPROS", publication.name, True])
        for subscription in self.subscriptions.values():
            for uri, inbound in subscription.connections.items():
                if inbound is not None and inbound.header is not None:
                    info.append([next(self._ids), uri, "i", "TCPROS", subscription.name, True])
        return info
