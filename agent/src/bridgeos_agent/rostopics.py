"""The topic side of a ROS 1 node on asyncio: TCPROS publications and subscriptions, bytes unparsed.

A Publication writes each burst of frames to its subscribers with one write per connection,
queueing (bounded) for a slow one; a Subscription connects to every publisher and hands each
burst of whole frames on as one ``bytes``. ``RosNode`` (rosnode.py) registers them with the
master and accepts the connections.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
from collections import deque
from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from bridgeos_agent.tcpros import HeaderError, decode_header, encode_header, split_frames

if TYPE_CHECKING:
    from bridgeos_agent.rosnode import RosNode

__all__ = [
    "Inbound",
    "MessageCallback",
    "Outbound",
    "Publication",
    "Subscription",
    "iter_frames",
    "nodelay",
    "read_header",
]

logger = logging.getLogger(__name__)

QUEUE_MESSAGES = 1000  # per subscriber connection, once its socket stops taking data...
QUEUE_BYTES = 16 << 20  # ...and at most this much of it (a thousand pointclouds would not fit a robot)
HIGH_WATER = 1 << 20  # bytes the kernel-side write buffer may hold before a connection queues
# Writes this big go to the transport as a view: asyncio keeps the unsent rest of a ``bytes`` as a
# copied slice and then copies that again into its buffer; a view saves the first copy (a 35 MB
# pointcloud's peak memory in the router drops by one cloud).
BIG_WRITE = 1 << 20
# A publisher whose bursts arrive closer than this is read in bursts of COALESCE_S instead: one
# wakeup per message would cost the router several µs of CPU each (throughput under load beats a
# fraction of a millisecond there; at nominal rates nothing waits).
COALESCE_GAP_S = 0.0002
COALESCE_S = 0.0005

MessageCallback = Callable[["Subscription", bytes, int, "Inbound"], None]


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


def nodelay(transport: asyncio.BaseTransport) -> None:
    """Send small TCP writes at once (ROS asks for tcp_nodelay on every topic connection)."""
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
                self.transport.write(memoryview(blob) if len(blob) >= BIG_WRITE else blob)
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
                self.transport.write(memoryview(data) if len(data) >= BIG_WRITE else data)
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
        self._wanted = 0  # bytes the buffer must hold before its first frame is whole
        self._last = 0.0
        self._loop = asyncio.get_running_loop()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]
        nodelay(transport)
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
        transport = self.transport
        assert transport is not None  # data arrives only after connection_made
        now = self._loop.time()
        if now - self._last < COALESCE_GAP_S and self.header is not None:
            transport.pause_reading()
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
                transport.close()
                return
            del buffer[: 4 + size]
            if "error" in header:
                logger.warning("%s: %s refused: %s", self.subscription.name, self.publisher, header["error"])
                transport.close()
                return
            self.header = header
            self.subscription.on_header(self)
            if not buffer:
                return
            data = bytes(buffer)
            buffer.clear()
        elif buffer:
            # A big message arrives in many reads: collect them, and look at the frames only once
            # it is whole (copying and scanning the buffer on every read would be quadratic).
            buffer += data
            if len(buffer) < self._wanted:
                return
            data = bytes(buffer)
            buffer.clear()
        try:
            end, count = split_frames(data)
        except HeaderError as exc:
            logger.warning("%s: %s", self.subscription.name, exc)
            transport.close()
            return
        if end < len(data):
            buffer += memoryview(data)[end:]
            # The incomplete frame's length, once its 4-byte prefix is here.
            self._wanted = 4 + int.from_bytes(buffer[:4], "little") if len(buffer) >= 4 else 4
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
