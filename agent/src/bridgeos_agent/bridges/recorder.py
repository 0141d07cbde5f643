"""Record a robot's topics into MCAP (profiles ``ros1`` / ``ros2``) and send the file to the cloud in chunks.

The recorder reads the graph through ``BridgeGraph`` and writes each message's wire bytes as they
came (ROS 1 serialized, or CDR), with the type's schema: ROS 1 ``ros1msg`` text as a publisher
announces it, ROS 2 ``ros2msg`` text from the installed ``.msg`` files with every type they use
appended as rosbag2 does. The MCAP bytes leave in chunks through the agent's outbox, so a
recording crosses a disconnection whole: every chunk stays on disk until the cloud acks it.

``McapRecording`` is the part without I/O (messages in, chunks out, limits); ``Recordings`` joins
it to the graphs and to the cloud link.

An agent killed mid-recording cannot finish its file, but its chunks are in the outbox already. A
small journal per running recording (``<data dir>/recordings/<id>.json``: how many chunks reached
the outbox) lets the next run end it: it reports the recording ``failed``, cut short, with that
many chunks, and the cloud assembles and repairs the file from them.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import importlib.util
import json
import logging
import os
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from bridgeos_agent.bridges.graph import BridgeError, BridgeGraph, GraphSubscription, Sample
from bridgeos_agent.bridges.ros2defs import message_definition
from bridgeos_agent.protocol import (
    RECORDING_CHUNK_BYTES,
    Envelope,
    Event,
    ProtocolError,
    RecordingStart,
)
from bridgeos_agent.protocol import RecordingStatusName as RS
from bridgeos_agent.tasks import TaskOwner

__all__ = ["McapRecording", "RecorderHost", "Recordings"]

logger = logging.getLogger("bridgeos_agent")

# MCAP chunk records of 64 KiB: small enough that a slow topic's data reaches the outbox often.
MCAP_CHUNK_SIZE = 64 * 1024
# How long a ROS 2 graph joined just now is given to discover the topics asked for.
DISCOVERY_S = 3.0


# --------------------------------------------------------------------------- MCAP without I/O


class _Sink:
    """The stream the MCAP writer writes to: bytes kept until taken as chunks."""

    def __init__(self) -> None:
        self.buffer = bytearray()
        self.position = 0

    def write(self, data: bytes) -> int:
        self.buffer += data
        self.position += len(data)
        return len(data)

    def tell(self) -> int:
        return self.position

    def flush(self) -> None:
        return None

    def close(self) -> None:
        return None


Schema = tuple[str, str]  # (schema encoding, schema text)


class McapRecording:
    """One MCAP file being written: messages in, chunks of at most ``chunk_bytes`` out, limits kept."""

    def __init__(
        self,
        ros: str,
        *,
        max_bytes: int,
        max_duration_ns: int,
        started_ns: int,
        chunk_bytes: int = RECORDING_CHUNK_BYTES,
        mcap_chunk_size: int = MCAP_CHUNK_SIZE,
    ) -> None:
        from mcap.writer import CompressionType, Writer

        self.ros = ros
        self.max_bytes = max_bytes
        self.deadline_ns = started_ns + max_duration_ns
        self.started_ns = started_ns
        self.chunk_bytes = chunk_bytes
        self.messages = 0
        self.bytes = 0  # message bytes recorded (what max_bytes limits)
        self.counts: dict[str, int] = {}
        self._sink = _Sink()
        self._writer = Writer(
            self._sink,  # type: ignore[arg-type]  # write/tell/flush is all it uses
            chunk_size=mcap_chunk_size,
            compression=CompressionType.ZSTD,
        )
        self._writer.start(profile=ros, library="bridgeos-agent")
        self._channels: dict[str, int] = {}
        self._schemas: dict[str, int] = {}
        self._sequence = 0
        self.closed = False

    @property
    def message_encoding(self) -> str:
        return "ros1" if self.ros == "ros1" else "cdr"

    def add(self, topic: str, type_: str, schema: Callable[[], Schema], raw: bytes, stamp_ns: int) -> bool:
        """Write one message; return False, writing nothing, when it would pass the size or time limit."""
        if self.closed:
            return False
        if stamp_ns > self.deadline_ns or self.bytes + len(raw) > self.max_bytes:
            return False
        channel = self._channels.get(topic)
        if channel is None:
            schema_id = self._schemas.get(type_)
            if schema_id is None:
                encoding, text = schema()
                schema_id = self._schemas[type_] = self._writer.register_schema(type_, encoding, text.encode())
            channel = self._channels[topic] = self._writer.register_channel(topic, self.message_encoding, schema_id)
        self._writer.add_message(channel, stamp_ns, raw, stamp_ns, sequence=self._sequence)
        self._sequence += 1
        self.messages += 1
        self.bytes += len(raw)
        self.counts[topic] = self.counts.get(topic, 0) + 1
        return True

    def take(self) -> list[bytes]:
        """Return the full chunks written so far."""
        return self._cut(final=False)

    def finish(self) -> list[bytes]:
        """End the file (its summary and footer) and return every chunk not yet taken."""
        if not self.closed:
            self.closed = True
            self._writer.finish()
        return self._cut(final=True)

    def _cut(self, *, final: bool) -> list[bytes]:
        buffer, size = self._sink.buffer, self.chunk_bytes
        whole = len(buffer) if final else len(buffer) - len(buffer) % size
        chunks = [bytes(buffer[i : i + size]) for i in range(0, whole, size)]
        del buffer[:whole]
        return chunks


# --------------------------------------------------------------------------- the agent's recordings


class RecorderHost(Protocol):
    """What the recorder needs of the Robot Controller."""

    ros_master: str | None
    ros2_graph: Any
    data_dir: Path

    async def emit(self, event: Event, data: Mapping[str, Any], *, reply_to: str | None = None) -> Envelope:
        """Send a frame to the cloud, kept on disk until acked."""


@dataclass
class _Active:
    """A recording running on this robot, with its subscriptions and its queue of frames to the cloud."""

    id: str
    ros: str
    mcap: McapRecording
    started_at: float
    queue: asyncio.Queue[tuple[Event, dict[str, Any]] | None] = field(default_factory=asyncio.Queue)
    subscriptions: list[GraphSubscription] = field(default_factory=list)
    seq: int = 0
    finished: bool = False
    sender: asyncio.Task[Any] | None = None
    timer: asyncio.Task[Any] | None = None


class Recordings:
    """The robot's MCAP recordings: start and stop on the cloud's orders, limits, chunks to the cloud."""

    def __init__(
        self,
        host: RecorderHost,
        *,
        clock: Callable[[], int] = time.time_ns,
        chunk_bytes: int = RECORDING_CHUNK_BYTES,
        mcap_chunk_size: int = MCAP_CHUNK_SIZE,
    ) -> None:
        if not 0 < chunk_bytes <= RECORDING_CHUNK_BYTES:
            raise ValueError(f"chunk_bytes must be 1..{RECORDING_CHUNK_BYTES}")
        self.host = host
        self.clock = clock
        self.chunk_bytes = chunk_bytes
        self.mcap_chunk_size = mcap_chunk_size
        self.active: dict[str, _Active] = {}
        self.done: set[str] = set()  # ids of recordings this agent ended (a late stop is then a no-op)
        self.tasks = TaskOwner()
        self._graphs: dict[str, BridgeGraph] = {}
        self._opening = asyncio.Lock()
        self.journal = Path(host.data_dir) / "recordings"

    # ------------------------------------------------------------------ graphs

    def available(self) -> list[str]:
        """Name the graphs this robot can record from."""
        found = []
        if self.host.ros_master:
            found.append("ros1")
        if self.host.ros2_graph is not None:
            found.append("ros2")
        return found

    async def _graph(self, ros: str) -> BridgeGraph:
        async with self._opening:
            graph = self._graphs.get(ros)
            if graph is not None:
                return graph
            if ros == "ros1":
                from bridgeos_agent.bridges.ros1graph import Ros1Graph

                host = os.environ.get("ROS_IP") or os.environ.get("ROS_HOSTNAME") or "127.0.0.1"
                graph1 = Ros1Graph(str(self.host.ros_master), name="/bridgeos_recorder", host=host)
                try:
                    await graph1.start()
                except Exception as exc:
                    raise ProtocolError(f"the ROS master does not answer: {exc}", code="unavailable") from None
                opened: BridgeGraph = graph1
            else:
                from bridgeos_agent.bridges.ros2graph import Ros2BridgeGraph

                opened = Ros2BridgeGraph(self.host.ros2_graph, asyncio.get_running_loop(), name="bridgeos_recorder")
            self._graphs[ros] = opened
            return opened

    async def _find(self, ros: str, topics: list[str]) -> tuple[BridgeGraph, dict[str, str], list[str]]:
        """Return the graph, the types of the topics it has and those it lacks (ROS 2 waits for discovery)."""
        graph = await self._graph(ros)
        deadline = time.monotonic() + (DISCOVERY_S if ros == "ros2" else 0.0)
        while True:
            try:
                known = await graph.topics()
            except BridgeError as exc:
                raise ProtocolError(str(exc), code="unavailable") from None
            missing = [topic for topic in topics if topic not in known]
            if not missing or time.monotonic() >= deadline:
                return graph, {t: known[t] for t in topics if t in known}, missing
            await asyncio.sleep(0.1)

    async def _resolve(self, ros: str | None, topics: list[str]) -> tuple[str, BridgeGraph, dict[str, str]]:
        available = self.available()
        if ros is not None and ros not in available:
            raise ProtocolError(f"this robot has no {ros.upper()} graph to record from", field="data.ros")
        candidates = [ros] if ros is not None else available
        if not candidates:
            raise ProtocolError("this robot has no ROS graph to record from", field="data.ros")
        fewest: list[str] | None = None
        for name in candidates:
            graph, types, missing = await self._find(name, topics)
            if not missing:
                return name, graph, types
            if fewest is None or len(missing) < len(fewest):
                fewest = missing
        unknown = ", ".join(fewest or topics)
        raise ProtocolError(f"unknown topic(s) on this robot: {unknown}", field="data.topics", code="not_found")

    def _schema(self, ros: str, graph: BridgeGraph, type_: str) -> Callable[[], Schema]:
        def schema() -> Schema:
            if ros == "ros1":
                return "ros1msg", graph.types.definition(type_)[0]  # type: ignore[attr-defined]
            return "ros2msg", message_definition(type_)

        return schema

    # ------------------------------------------------------------------ orders

    async def start(self, order: RecordingStart) -> None:
        """Start recording, or raise ProtocolError naming what is wrong (nothing is then started)."""
        if order.recording in self.active or order.recording in self.done:
            return  # the same order again (the cloud resent it): already done
        if importlib.util.find_spec("mcap") is None:
            raise ProtocolError(
                "MCAP recording needs mcap: pip install 'bridgeos-agent[rosbridge]'", code="unsupported"
            )
        topics = list(dict.fromkeys(order.topics))
        ros, graph, types = await self._resolve(order.ros, topics)
        schemas = {type_: self._schema(ros, graph, type_) for type_ in set(types.values())}
        if ros == "ros2":
            for schema in schemas.values():
                try:
                    schema()  # a type without an installed definition is refused now, not mid-recording
                except BridgeError as exc:
                    raise ProtocolError(str(exc), field="data.topics", code="not_found") from None
        started = self.clock()
        active = _Active(
            order.recording,
            ros,
            McapRecording(
                ros,
                max_bytes=order.max_bytes,
                max_duration_ns=int(order.max_duration_s * 1e9),
                started_ns=started,
                chunk_bytes=self.chunk_bytes,
                mcap_chunk_size=self.mcap_chunk_size,
            ),
            started / 1e9,
        )
        try:
            for topic, type_ in types.items():
                deliver = self._deliverer(active, topic, type_, schemas[type_])
                active.subscriptions.append(await graph.subscribe(topic, type_, deliver))
        except BridgeError as exc:
            for subscription in active.subscriptions:
                subscription.close()
            raise ProtocolError(str(exc), field="data.topics") from None
        self.active[order.recording] = active
        self._write_journal(active, chunks=0)
        active.sender = self.tasks.spawn(self._send(active), name=f"recording {order.recording}")
        active.timer = self.tasks.spawn(self._expire(active, order.max_duration_s))
        active.queue.put_nowait(
            (
                Event.RECORDING_STATUS,
                {"recording": active.id, "status": str(RS.RECORDING), "ros": ros, "started_at": active.started_at},
            )
        )
        logger.info("recording %s of %s (%s) started", order.recording, ", ".join(topics), ros)

    async def stop(self, recording: str) -> None:
        """End a recording on the cloud's order (a recording already ended is left as it is)."""
        if recording in self.done:
            return
        if recording not in self.active:
            raise ProtocolError(f"no recording {recording} on this robot", field="data.recording", code="not_found")
        self._finish(self.active[recording], "stopped")

    def _deliverer(
        self, active: _Active, topic: str, type_: str, schema: Callable[[], Schema]
    ) -> Callable[[Sample], None]:
        def deliver(sample: Sample) -> None:
            if active.finished:
                return
            stamp = sample.stamp[0] * 1_000_000_000 + sample.stamp[1]
            try:
                written = active.mcap.add(topic, type_, schema, bytes(sample.raw), stamp)
            except BridgeError as exc:
                self._finish(active, f"failed: {exc}", failed=True)
                return
            if not written:
                over_time = stamp > active.mcap.deadline_ns
                self._finish(active, "duration limit reached" if over_time else "size limit reached")
                return
            self._queue_chunks(active, active.mcap.take())

        return deliver

    async def _expire(self, active: _Active, seconds: float) -> None:
        await asyncio.sleep(seconds)
        self._finish(active, "duration limit reached")

    def _queue_chunks(self, active: _Active, chunks: list[bytes]) -> None:
        for chunk in chunks:
            data = {"recording": active.id, "seq": active.seq, "data": base64.b64encode(chunk).decode()}
            active.queue.put_nowait((Event.RECORDING_CHUNK, data))
            active.seq += 1

    def _finish(self, active: _Active, reason: str, *, failed: bool = False) -> None:
        """End a recording: leave its topics, close the file and queue its last chunks and its totals."""
        if active.finished:
            return
        active.finished = True
        for subscription in active.subscriptions:
            with contextlib.suppress(Exception):  # a graph already gone has nothing left to leave
                subscription.close()
        if active.timer is not None and active.timer is not asyncio.current_task():
            active.timer.cancel()
        self._queue_chunks(active, active.mcap.finish())
        mcap = active.mcap
        status = {
            "recording": active.id,
            "status": str(RS.FAILED if failed else RS.FINISHED),
            "ros": active.ros,
            "message": reason,
            "started_at": active.started_at,
            "stopped_at": self.clock() / 1e9,
            "messages": mcap.messages,
            "bytes": mcap.bytes,
            "chunks": active.seq,
        }
        active.queue.put_nowait((Event.RECORDING_STATUS, status))
        active.queue.put_nowait(None)
        self.done.add(active.id)
        logger.info("recording %s ended (%s): %d message(s), %d chunk(s)", active.id, reason, mcap.messages, active.seq)

    async def _send(self, active: _Active) -> None:
        """Hand the recording's frames to the outbox in order; it keeps each until the cloud acks it."""
        try:
            while (item := await active.queue.get()) is not None:
                await self.host.emit(*item)
                event, data = item
                if event == Event.RECORDING_CHUNK:
                    self._write_journal(active, chunks=data["seq"] + 1)  # after the outbox holds it, never before
                elif data.get("status") in (RS.FINISHED, RS.FAILED):
                    self._journal_path(active.id).unlink(missing_ok=True)
        finally:
            self.active.pop(active.id, None)

    # ------------------------------------------------------------------ the journal of running recordings

    def _journal_path(self, recording: str) -> Path:
        return self.journal / f"{recording}.json"

    def _write_journal(self, active: _Active, *, chunks: int) -> None:
        """Note how many of a running recording's chunks the outbox holds (read by the next run if we die)."""
        entry = {
            "recording": active.id,
            "ros": active.ros,
            "started_at": active.started_at,
            "chunks": chunks,
            "messages": active.mcap.messages,
            "bytes": active.mcap.bytes,
        }
        self.journal.mkdir(parents=True, exist_ok=True)
        path = self._journal_path(active.id)
        partial = path.with_suffix(".tmp")
        partial.write_text(json.dumps(entry))
        os.replace(partial, path)

    async def recover(self) -> int:
        """End the recordings a previous run left running (it was killed): cut short, with the chunks it sent."""
        ended = 0
        for path in sorted(self.journal.glob("*.json")) if self.journal.is_dir() else []:
            try:
                entry = json.loads(path.read_text())
                status = {
                    "recording": str(entry["recording"]),
                    "status": str(RS.FAILED),
                    "ros": entry.get("ros"),
                    "message": (
                        "cut short: the agent stopped without ending it; "
                        f"the file holds what reached the cloud ({int(entry['chunks'])} chunk(s))"
                    ),
                    "started_at": entry.get("started_at"),
                    "stopped_at": path.stat().st_mtime,
                    "messages": int(entry.get("messages", 0)),
                    "bytes": int(entry.get("bytes", 0)),
                    "chunks": int(entry["chunks"]),
                }
            except (OSError, ValueError, KeyError, TypeError) as exc:
                logger.warning("recording journal %s is unreadable (%s); removed", path.name, exc)
                path.unlink(missing_ok=True)
                continue
            await self.host.emit(Event.RECORDING_STATUS, status)
            path.unlink(missing_ok=True)
            self.done.add(status["recording"])
            ended += 1
            logger.warning(
                "recording %s was cut short by the agent's restart: %s", status["recording"], status["message"]
            )
        return ended

    # ------------------------------------------------------------------ life cycle

    async def close(self) -> None:
        """End every recording (its last chunks go to the outbox), then leave the graphs."""
        for active in list(self.active.values()):
            self._finish(active, "the agent stopped")
        senders = [a.sender for a in self.active.values() if a.sender is not None]
        if senders:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(asyncio.gather(*senders, return_exceptions=True), 5)
        await self.tasks.close()
        for graph in self._graphs.values():
            with contextlib.suppress(Exception):
                await graph.close()
        self._graphs.clear()
