"""The cloud's bridge clients served over the robot's own link: one engine session per client.

The cloud opens a session (``bridge_open``) for each client of ``/ws/rosbridge/<robot>/`` or
``/ws/foxglove/<robot>/`` and carries its WebSocket frames both ways (``bridge_frame``); either
side ends it (``bridge_close``). Every session of a kind shares one engine, and every engine the
agent's one graph, so a topic is subscribed in the graph once however many clients watch it.

Batches: when the cloud takes them, the frames a session's engine writes in one go (a busy topic's
queue, drained) travel as one ``bridge_frame`` (``texts``/``binaries``) instead of one envelope
each, which is most of the per-message cost on both ends of the link.

Flow: each session writes through a byte budget (the cloud's per-client cap). A client over its
cap makes its session's writer wait, so its engine queues fill and drop their oldest messages
(counted), while the robot's graph and the other sessions go on at their own pace.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import functools
import importlib
import logging
import time
from collections.abc import Awaitable, Callable, Mapping
from typing import Any, Protocol

from bridgeos_agent.bridges.graph import BridgeGraph
from bridgeos_agent.protocol import (
    BRIDGE_BINARY_CHARS,
    BRIDGE_BLOB_MAX_BYTES,
    BRIDGE_BLOB_MIN_BYTES,
    BRIDGE_HEAD_BYTES,
    BRIDGE_PART_CHARS,
    BlobWindow,
    Event,
    encode_bridge_blob,
)

__all__ = ["ENGINES", "BridgeRelay", "ByteBudget", "FrameAssembler", "frame_parts", "whole_frames"]

logger = logging.getLogger(__name__)

# Where each kind's engine lives: a class taking the graph, whose .session(send) serves one client.
ENGINES: Mapping[str, tuple[str, str]] = {
    "rosbridge": ("bridgeos_agent.bridges.rosbridge", "Rosbridge"),
    "foxglove": ("bridgeos_agent.bridges.foxglove", "Foxglove"),
}
MAX_SESSIONS = 64  # clients of one robot at once
MAX_INBOX = 1_000  # client frames waiting for their session; more is a flood and ends the session
MAX_CLIENT_FRAME = 16 << 20  # a client frame reassembled from parts may not exceed this
BATCH_FRAME_BYTES = 16 * 1024  # a frame larger than this goes alone (in parts if need be), not batched

SendEvent = Callable[[Event, dict[str, Any]], Awaitable[Any]]
SendBinary = Callable[[bytes], Awaitable[Any]]
Send = Callable[[str | bytes], Awaitable[None]]


class EngineSession(Protocol):
    async def receive(self, frame: str | bytes) -> None: ...

    async def close(self) -> None: ...


class Engine(Protocol):
    def session(self, send: Send) -> EngineSession: ...

    async def close(self) -> None: ...


class ByteBudget:
    """A token bucket over bytes: how long to wait before sending a frame of some size."""

    def __init__(self, rate: float, burst: float, now: float) -> None:
        self.rate = rate
        self.burst = burst
        self.tokens = burst
        self.at = now

    def delay(self, size: int, now: float) -> float:
        """Spend ``size`` bytes; return how many seconds to wait first (a big frame goes into debt)."""
        self.tokens = min(self.burst, self.tokens + (now - self.at) * self.rate)
        self.at = now
        wait = 0.0 if self.tokens >= 0 else -self.tokens / self.rate
        self.tokens -= size
        return wait


class _Session:
    """One client's session: its engine session, the frames waiting for it, its writer's budget."""

    def __init__(
        self, relay: BridgeRelay, ident: str, bytes_per_s: int | None, batches: bool = False, blobs: bool = False
    ) -> None:
        self.relay = relay
        self.batches = batches
        self.blobs = blobs
        self.pending: list[str | bytes] = []  # whole frames of one type waiting for the next batch
        self.pending_chars = 0
        self.pending_dropped = 0
        self.flushing: asyncio.Task[None] | None = None
        self.sending = asyncio.Lock()  # batches and lone frames leave in the order they were written
        self.ident = ident
        self.engine_session: EngineSession | None = None
        self.inbox: asyncio.Queue[str | bytes] = asyncio.Queue()
        self.assembler = FrameAssembler(MAX_CLIENT_FRAME)
        self.budget = ByteBudget(bytes_per_s, bytes_per_s, time.monotonic()) if bytes_per_s else None
        self.tasks: list[asyncio.Task[Any]] = []
        self.sent_bytes = 0
        self.closed = False
        self.drops_reported = 0  # of the engine session's drops, told to the cloud
        self.drops_checked = 0.0

    def new_drops(self, now: float) -> int:
        """Return the engine's drops for this client not yet told to the cloud (looked at once a second)."""
        if now - self.drops_checked < 1.0 or self.engine_session is None:
            return 0
        self.drops_checked = now
        stats = getattr(self.engine_session, "stats", None)
        total = sum(topic["dropped"] for topic in stats().values()) if stats is not None else 0
        new, self.drops_reported = max(0, total - self.drops_reported), total
        return new

    async def send(self, frame: str | bytes) -> None:
        """Send one engine frame to the client, in parts when large, within the client's byte budget."""
        if self.closed:
            return
        now = time.monotonic()
        if self.budget is not None:
            wait = self.budget.delay(len(frame), now)
            if wait > 0:
                await asyncio.sleep(wait)
        dropped = self.new_drops(now)
        self.sent_bytes += len(frame)
        if self.blobs and BRIDGE_BLOB_MIN_BYTES <= len(frame):
            head, tail = shared_parts(frame)
            if len(head) <= BRIDGE_HEAD_BYTES and len(tail) <= BRIDGE_BLOB_MAX_BYTES:
                await self.flush()
                async with self.sending:
                    data: dict[str, Any] = {"session": self.ident, "blob": await self.relay.blob(tail)}
                    if head:
                        data["head"] = base64.b64encode(head).decode()
                    if dropped:
                        data["dropped"] = dropped
                    await self.relay.send_event(Event.BRIDGE_FRAME, data)
                return
        if not self.batches or len(frame) > BATCH_FRAME_BYTES:
            await self.flush()
            async with self.sending:
                for data in frame_parts(self.ident, frame):
                    if dropped:
                        data["dropped"], dropped = dropped, 0
                    await self.relay.send_event(Event.BRIDGE_FRAME, data)
            return
        chars = len(frame) if isinstance(frame, str) else (len(frame) + 2) // 3 * 4
        limit = BRIDGE_PART_CHARS if isinstance(frame, str) else BRIDGE_BINARY_CHARS
        if self.pending and (type(frame) is not type(self.pending[0]) or self.pending_chars + chars > limit):
            await self.flush()
        self.pending.append(frame)
        self.pending_chars += chars
        self.pending_dropped += dropped
        if self.flushing is None or self.flushing.done():
            # Runs once the engine's writer yields: everything it wrote until then goes as one batch.
            self.flushing = asyncio.ensure_future(self.flush())

    async def flush(self) -> None:
        """Send the frames waiting for a batch as one bridge_frame."""
        async with self.sending:
            if not self.pending or self.closed:
                return
            frames, self.pending, self.pending_chars = self.pending, [], 0
            data: dict[str, Any] = {"session": self.ident}
            if self.pending_dropped:
                data["dropped"], self.pending_dropped = self.pending_dropped, 0
            if isinstance(frames[0], str):
                data["texts"] = frames
            else:
                data["binaries"] = [base64.b64encode(frame).decode() for frame in frames if isinstance(frame, bytes)]
            await self.relay.send_event(Event.BRIDGE_FRAME, data)

    async def read(self) -> None:
        """Feed the client's frames to its engine session one at a time, in order."""
        assert self.engine_session is not None
        while True:
            frame = await self.inbox.get()
            await self.engine_session.receive(frame)


class FrameAssembler:
    """Put a frame back together from its bridge_frame parts, refusing one larger than ``limit`` bytes."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.parts: list[Any] = []
        self.size = 0

    def take(self, data: Any) -> str | bytes | list[str] | list[bytes] | None:
        """Add a part (a BridgeFrame); return the whole frame after its last part, or a batch's frames.

        ValueError: the frame is too big, or a batch cut into a frame's parts.
        """
        whole = whole_frames(data)
        if whole is not None:
            if self.parts:
                self.parts, self.size = [], 0
                raise ValueError("a batch of frames came between the parts of a frame")
            return whole
        part: str | bytes = data.text if data.text is not None else base64.b64decode(data.binary)
        self.size += len(part)
        if self.size > self.limit:
            self.parts, self.size = [], 0
            raise ValueError(f"a frame exceeds {self.limit} bytes")
        if data.more:
            self.parts.append(part)
            return None
        parts, self.parts, self.size = self.parts, [], 0
        if not parts:
            return part
        parts.append(part)
        return "".join(parts) if isinstance(part, str) else b"".join(parts)


def whole_frames(data: Any) -> list[str] | list[bytes] | None:
    """Return a batch bridge_frame's frames in order (binary ones decoded), or None for a lone frame."""
    if data.texts is not None:
        return list(data.texts)
    if data.binaries is not None:
        return [base64.b64decode(frame) for frame in data.binaries]
    return None


def shared_parts(frame: str | bytes) -> tuple[bytes, str | bytes | memoryview]:
    """Split a frame into its client's own head and the tail other clients' frames may share.

    An engine that shares a message's bytes across clients marks its frame a SharedTail; any other
    frame is all tail, shared when the engine hands every client the same object (rosbridge caches
    one encoding of a message for all its clients).
    """
    tail = getattr(frame, "tail", None)
    if tail is not None:
        return frame.head, tail  # type: ignore[union-attr]
    return b"", frame


def frame_parts(ident: str, frame: str | bytes) -> list[dict[str, Any]]:
    """Split a session's frame into bridge_frame payloads small enough for one envelope each."""
    size = BRIDGE_PART_CHARS if isinstance(frame, str) else (BRIDGE_PART_CHARS // 4) * 3
    pieces = [frame[i : i + size] for i in range(0, len(frame), size)] or [frame]
    out = []
    for index, piece in enumerate(pieces):
        data: dict[str, Any] = {"session": ident, "more": index < len(pieces) - 1}
        if isinstance(piece, str):
            data["text"] = piece
        else:
            data["binary"] = base64.b64encode(piece).decode()
        out.append(data)
    return out


class BridgeRelay:
    """Serve the cloud's bridge sessions on this robot's graph, opened on the first client."""

    def __init__(
        self,
        send_event: SendEvent,
        open_graph: Callable[[], Awaitable[BridgeGraph]],
        *,
        engines: Mapping[str, tuple[str, str]] = ENGINES,
        engine_options: Mapping[str, Mapping[str, Any]] | None = None,
        max_sessions: int = MAX_SESSIONS,
        send_binary: SendBinary | None = None,
    ) -> None:
        self.send_event = send_event
        self.send_binary = send_binary
        self._open_graph = open_graph
        self.engine_specs = engines
        self.engine_options = dict(engine_options or {})
        self.max_sessions = max_sessions
        self.graph: BridgeGraph | None = None
        self.engines: dict[str, Engine] = {}
        self.sessions: dict[str, _Session] = {}
        self._setup = asyncio.Lock()
        self._background: set[asyncio.Future[Any]] = set()  # starts and ends in the background, owned until done
        # The blobs the cloud holds, as it will count them: by the shared object's id (the entry keeps
        # the object alive, so the id is not reused), with the future of its sending.
        self.window = BlobWindow()
        self._blobs: dict[int, tuple[int, object, asyncio.Future[None]]] = {}
        self._blob_keys: dict[int, int] = {}  # blob id -> key in _blobs
        self._next_blob = 0
        self._blob_sending = asyncio.Lock()
        self.blobs_sent = 0
        self.blob_bytes_sent = 0

    def open(
        self, ident: str, kind: str, bytes_per_s: int | None = None, *, batches: bool = False, blobs: bool = False
    ) -> None:
        """Start a client's session of a kind; its frames queue until the engine is ready.

        ``batches``: the cloud takes several whole frames in one bridge_frame; ``blobs``: it takes
        blobs, so a large frame shared by several clients crosses the link once.
        """
        if ident in self.sessions:
            return
        if len(self.sessions) >= self.max_sessions:
            self._spawn(self._refuse(ident, f"the robot serves at most {self.max_sessions} bridge clients at once"))
            return
        # Registered now, before the graph is joined, so the frames right behind the open wait for it.
        session = self.sessions[ident] = _Session(self, ident, bytes_per_s, batches, blobs and bool(self.send_binary))
        self._spawn(self._start(session, kind))

    async def _start(self, session: _Session, kind: str) -> None:
        try:
            engine = await self._engine(kind)
        except Exception as exc:
            if not session.closed:
                await self.end(session.ident, str(exc) or type(exc).__name__, tell=True)
            return
        if session.closed:  # closed by the cloud while the graph was being joined
            return
        session.engine_session = engine.session(session.send)
        loop = asyncio.get_running_loop()
        session.tasks.append(loop.create_task(session.read(), name=f"bridge {session.ident} reader"))
        run = getattr(session.engine_session, "run", None)
        if run is not None:
            session.tasks.append(loop.create_task(run(), name=f"bridge {session.ident} writer"))
        for task in session.tasks:
            task.add_done_callback(functools.partial(self._task_ended, session.ident))

    def receive(self, data: Any) -> None:
        """Queue a client frame (or part of one) for its session, in arrival order."""
        session = self.sessions.get(data.session)
        if session is None or session.closed:
            return  # closed here already; the cloud hears of it from our bridge_close
        try:
            frame = session.assembler.take(data)
        except ValueError as exc:
            self._close_soon(data.session, str(exc))
            return
        if frame is None:
            return
        for whole in frame if isinstance(frame, list) else [frame]:
            if session.inbox.qsize() >= MAX_INBOX:
                self._close_soon(data.session, f"more than {MAX_INBOX} client frames waiting: flooding")
                return
            session.inbox.put_nowait(whole)

    async def end(self, ident: str, reason: str = "", *, tell: bool = False) -> None:
        """End one session (and tell the cloud, when the robot ends it)."""
        session = self.sessions.pop(ident, None)
        if session is None or session.closed:
            return
        session.closed = True
        if session.flushing is not None:
            session.flushing.cancel()
        current = asyncio.current_task()
        for task in session.tasks:
            if task is not current:
                task.cancel()
        for task in session.tasks:
            if task is not current:
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
        if session.engine_session is not None:
            await session.engine_session.close()
        if tell:
            await self._refuse(ident, reason)

    async def close_sessions(self) -> None:
        """End every session: the link they travelled on is gone, and the cloud's blobs with it."""
        self.forget_blobs()
        for ident in list(self.sessions):
            await self.end(ident)

    def forget_blobs(self) -> None:
        """Forget which blobs the cloud holds: a new link starts with none."""
        self.window.clear()
        self._blobs.clear()
        self._blob_keys.clear()

    async def blob(self, tail: str | bytes | memoryview) -> int:
        """Return the id of the blob carrying ``tail``, sending it first unless the cloud holds it."""
        entry = self._blobs.get(id(tail))
        if entry is not None and entry[1] is tail:
            await asyncio.shield(entry[2])  # another client's frame is sending it right now
            return entry[0]
        ident = self._next_blob
        self._next_blob = (ident + 1) & 0xFFFFFFFF
        messages = encode_bridge_blob(ident, tail)
        sent = asyncio.get_running_loop().create_future()
        self._blobs[id(tail)] = (ident, tail, sent)
        self._blob_keys[ident] = id(tail)
        for gone in self.window.add(ident, sum(len(message) for message in messages)):
            key = self._blob_keys.pop(gone, None)
            if key is not None and self._blobs.get(key, (None,))[0] == gone:
                del self._blobs[key]
        try:
            assert self.send_binary is not None
            async with self._blob_sending:  # one blob's parts at a time: the cloud puts them together in order
                for message in messages:
                    await self.send_binary(message)
                    self.blob_bytes_sent += len(message)
            self.blobs_sent += 1
        finally:
            if not sent.done():
                sent.set_result(None)
        return ident

    async def shutdown(self) -> None:
        """End every session, the engines and the graph (the agent stops)."""
        await self.close_sessions()
        for task in list(self._background):
            task.cancel()
        for engine in self.engines.values():
            with contextlib.suppress(Exception):
                await engine.close()
        self.engines.clear()
        if self.graph is not None:
            with contextlib.suppress(Exception):
                await self.graph.close()
            self.graph = None

    def stats(self) -> dict[str, int]:
        """Return how many sessions are open and the bytes sent to their clients."""
        return {
            "sessions": len(self.sessions),
            "sent_bytes": sum(s.sent_bytes for s in self.sessions.values()),
            "blobs_sent": self.blobs_sent,
            "blob_bytes_sent": self.blob_bytes_sent,
        }

    # ------------------------------------------------------------------ internals

    async def _engine(self, kind: str) -> Engine:
        async with self._setup:
            engine = self.engines.get(kind)
            if engine is not None:
                return engine
            spec = self.engine_specs.get(kind)
            if spec is None:
                raise ValueError(f"this robot's agent has no {kind} engine")
            try:
                engine_class = getattr(importlib.import_module(spec[0]), spec[1])
            except (ImportError, AttributeError):
                raise ValueError(f"this robot's agent has no {kind} engine (upgrade bridgeos-agent)") from None
            if self.graph is None:
                self.graph = await self._open_graph()
            engine = self.engines[kind] = engine_class(self.graph, **self.engine_options.get(kind, {}))
            return engine

    async def _refuse(self, ident: str, reason: str) -> None:
        await self.send_event(Event.BRIDGE_CLOSE, {"session": ident, "reason": reason[:500]})

    def _close_soon(self, ident: str, reason: str) -> None:
        self._spawn(self.end(ident, reason, tell=True))

    def _spawn(self, coroutine: Awaitable[Any]) -> None:
        task = asyncio.ensure_future(coroutine)
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    def _task_ended(self, ident: str, task: asyncio.Task[Any]) -> None:
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:
            logger.error("bridge session %s failed: %s", ident, exc, exc_info=exc)
            self._close_soon(ident, f"the robot's bridge failed: {type(exc).__name__}: {exc}")
