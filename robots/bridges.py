"""The cloud's bridge doors: /ws/rosbridge/<robot>/ and /ws/foxglove/<robot>/, relayed over the robot's link.

A client authenticates with `Authorization: Token <API token>` or a ticket from
`POST /api/robot/<robot>/bridge-ticket` (``?ticket=``); anyone else is refused at the handshake
exactly as for a robot that does not exist. Each client is one bridge session on the robot's
connection: its frames go to the robot consumer holding that connection (directly when it lives in
this process, else through the channel layer), which passes them to the agent, and back.

No viewer can hold up the robot or another viewer: the agent caps each session's bytes per
second (its engine's queues drop the oldest past it), and here each client has a bounded queue
(drop-oldest, counted) that the robot consumer only ever appends to, never waits on.
"""

from __future__ import annotations

import asyncio
import base64
import json
import logging
import secrets
import time
from collections import deque
from typing import Any
from urllib.parse import parse_qs

from channels.consumer import get_handler_name
from channels.db import database_sync_to_async
from channels.generic.websocket import AsyncWebsocketConsumer
from django.conf import settings

from audit import services as audit
from bridgeos_agent import protocol
from bridgeos_agent.bridges.relay import FrameAssembler, frame_parts
from bridgeos_agent.protocol import BlobWindow, Event
from bridgeos_cloud.ratelimit import TokenBucket
from monitoring import prometheus

from .access import open_bridge
from .local import deliver, register_local

log = logging.getLogger(__name__)

FOXGLOVE_SUBPROTOCOLS = ("foxglove.sdk.v1", "foxglove.websocket.v1")
CLOSE_ROBOT_OFFLINE = 4010  # the robot is not connected (or dropped while the client was on)
CLOSE_BRIDGE_ENDED = 4011  # the robot ended the session (no engine of that kind, no ROS graph, a fault)
CLOSE_FLOODING = 4008
OPEN_TIMEOUT_S = 5.0  # how long the robot's consumer has to take a new session
MAX_FLOOD_STRIKES = 500
MAX_SESSIONS_PER_ROBOT = 64


def status_frame(kind: str, text: str, level: str = "error") -> str:
    """Build the protocol's own status message: rosbridge's `status` or Foxglove's."""
    if kind == "foxglove":
        return json.dumps({"op": "status", "level": {"info": 0, "warning": 1, "error": 2}[level], "message": text})
    return json.dumps({"op": "status", "level": level, "msg": text})


def bridge_envelope(event: Event, data: dict[str, Any]) -> str:
    """Encode a bridge event for the robot's link."""
    return protocol.encode(protocol.make(event, data, now=time.time()))


class BridgeConsumer(AsyncWebsocketConsumer):
    """One rosbridge or Foxglove client of one robot."""

    kind = "rosbridge"

    async def dispatch(self, message: dict[str, Any]) -> None:
        # Without Channels' per-message hop to a thread: the database is reached only in connect.
        handler = getattr(self, get_handler_name(message), None)
        if handler is None:
            raise ValueError(f"no handler for message type {message['type']}")
        await handler(message)

    # ---------------------------------------------------------------- opening

    async def connect(self) -> None:
        self.robot_id: str = self.scope["url_route"]["kwargs"]["robot_id"]
        self.session = ""
        self.robot_channel = ""
        self.closing = False
        self.queue: deque[str | bytes] = deque()
        self.queue_frames = settings.BRIDGEOS["BRIDGE_CLIENT_QUEUE"]
        self.queue_bytes = settings.BRIDGEOS["BRIDGE_CLIENT_QUEUE_BYTES"]
        self.queued_bytes = 0
        self.dropped = 0
        self.wake = asyncio.Event()
        self.writer: asyncio.Task[None] | None = None
        self.opened: asyncio.TimerHandle | None = None
        self.ending: asyncio.Future[None] | None = None
        self.session_closed = False
        self.assembler = FrameAssembler(settings.BRIDGEOS["BRIDGE_MAX_FRAME_BYTES"] * 4)
        self.max_frame = settings.BRIDGEOS["BRIDGE_MAX_FRAME_BYTES"]
        self.bucket = TokenBucket(
            settings.BRIDGEOS["BRIDGE_CLIENT_FRAMES_PER_S"], settings.BRIDGEOS["BRIDGE_CLIENT_FRAME_BURST"], 0.0
        )
        self.bucket.updated = time.monotonic()
        self.flood_strikes = 0
        self.last_refused = 0.0
        self.counted = False  # in the bridge_clients gauge
        subprotocol = self.choose_subprotocol()
        if subprotocol is False:
            await self.close()  # a Foxglove door without a Foxglove subprotocol: a 403, like any refusal
            return
        token, ticket = self.credentials()
        access = await database_sync_to_async(open_bridge)(self.robot_id, token=token, ticket=ticket)
        await database_sync_to_async(audit.record_bridge_open)(
            self.kind, self.robot_id, access.user_id if access else None, self.scope.get("client")
        )
        if access is None:
            # Unknown robot, someone else's, bad or spent credentials: the same 403 for all.
            await self.close()
            return
        await self.accept(subprotocol)
        if not access.channel:
            await self.end(f"robot {self.robot_id} is offline", CLOSE_ROBOT_OFFLINE)
            return
        self.robot_channel = access.channel
        self.session = secrets.token_urlsafe(16)
        register_local(self)
        prometheus.BRIDGE_CLIENTS.labels(self.kind).inc()
        self.counted = True
        self.writer = asyncio.ensure_future(self.write())
        self.opened = asyncio.get_running_loop().call_later(OPEN_TIMEOUT_S, self.open_timed_out)
        cap = settings.BRIDGEOS["BRIDGE_CLIENT_BYTES_PER_S"]
        data = {"session": self.session, "kind": self.kind, "bytes_per_s": cap, "batches": True, "blobs": True}
        message = {
            "type": "robot.bridge",
            "session": self.session,
            "open": self.channel_name,
            "kind": self.kind,
            "frame": bridge_envelope(Event.BRIDGE_OPEN, data),
        }
        if not await deliver(self.robot_channel, message):
            await self.end(f"robot {self.robot_id} is not reachable right now", CLOSE_ROBOT_OFFLINE)

    def choose_subprotocol(self) -> str | bool | None:
        """Pick the Foxglove subprotocol the client offers (False: none offered); rosbridge has none."""
        if self.kind != "foxglove":
            return None
        offered = self.scope.get("subprotocols") or []
        return next((name for name in FOXGLOVE_SUBPROTOCOLS if name in offered), False)

    def credentials(self) -> tuple[str | None, str | None]:
        """Return the API token of an `Authorization: Token` header, or the query string's ticket."""
        headers = dict(self.scope.get("headers", []))
        header = headers.get(b"authorization", b"").decode("latin-1")
        scheme, _, value = header.partition(" ")
        if scheme.lower() == "token" and value.strip():
            return value.strip(), None
        query = parse_qs(self.scope.get("query_string", b"").decode("latin-1"))
        tickets = query.get("ticket") or [None]
        return None, tickets[0]

    def open_timed_out(self) -> None:
        self.opened = None
        self.ending = asyncio.ensure_future(self.end(f"robot {self.robot_id} did not answer", CLOSE_ROBOT_OFFLINE))

    # ---------------------------------------------------------------- client -> robot

    async def receive(self, text_data: str | None = None, bytes_data: bytes | None = None) -> None:
        frame: str | bytes = text_data if text_data is not None else (bytes_data or b"")
        if self.closing or not self.session:
            return
        size = len(frame) if isinstance(frame, bytes) else len(frame.encode("utf-8", "surrogatepass"))
        if size > self.max_frame:
            await self.tell(f"frame of {size} bytes exceeds the limit of {self.max_frame} bytes; it was dropped")
            return
        now = time.monotonic()
        if not self.bucket.allow(now):
            await self.flooded(now)
            return
        for data in frame_parts(self.session, frame):
            envelope = bridge_envelope(Event.BRIDGE_FRAME, data)
            message = {"type": "robot.bridge", "session": self.session, "frame": envelope}
            if not await deliver(self.robot_channel, message):
                await self.tell("the robot's connection is busy; the frame was dropped")
                return

    async def flooded(self, now: float) -> None:
        if now - self.last_refused > 1.0:
            self.flood_strikes = 0
        self.last_refused = now
        self.flood_strikes += 1
        if self.flood_strikes >= MAX_FLOOD_STRIKES:
            await self.end("too many frames, closing", CLOSE_FLOODING)
            return
        if self.flood_strikes == 1:  # said once per burst, not once per dropped frame
            rate = settings.BRIDGEOS["BRIDGE_CLIENT_FRAMES_PER_S"]
            await self.tell(f"too many frames: at most {rate:g} per second; frames over it are dropped")

    # ---------------------------------------------------------------- robot -> client

    async def bridge_opened(self, message: dict[str, Any]) -> None:
        """The robot's consumer took the session: it is the robot's to answer now."""
        if self.opened is not None:
            self.opened.cancel()
            self.opened = None

    async def bridge_frame(self, message: dict[str, Any]) -> None:
        """Queue a frame (part, or batch of frames) from the robot for the client, dropping the oldest when full."""
        whole = message.get("whole")
        if whole is not None:  # a blob's frame, put together by the robot's consumer
            self.enqueue(whole)
            return
        try:
            frame = self.assembler.take(protocol.BridgeFrame.model_validate(message["data"]))
        except ValueError as exc:
            await self.end(f"the robot sent a bad frame: {exc}", CLOSE_BRIDGE_ENDED)
            return
        if frame is None:
            return
        for one in frame if isinstance(frame, list) else [frame]:
            self.enqueue(one)

    def enqueue(self, frame: str | bytes) -> None:
        """Queue a frame for the client; past the queue's frames or bytes, the oldest go (counted)."""
        self.queue.append(frame)
        self.queued_bytes += len(frame)
        while len(self.queue) > 1 and (len(self.queue) > self.queue_frames or self.queued_bytes > self.queue_bytes):
            self.queued_bytes -= len(self.queue.popleft())
            self.dropped += 1
            prometheus.bridge_dropped(self.kind, "cloud_queue")
        self.wake.set()

    async def bridge_closed(self, message: dict[str, Any]) -> None:
        """The robot ended the session, or went offline."""
        self.session_closed = True
        if message.get("offline"):
            await self.end(f"robot {self.robot_id} went offline", CLOSE_ROBOT_OFFLINE)
        else:
            await self.end(message.get("reason") or "the robot ended the session", CLOSE_BRIDGE_ENDED)

    async def write(self) -> None:
        """Send queued frames to the client, oldest first."""
        while not self.closing:
            frames = size = 0
            while self.queue and not self.closing:
                frame = self.queue.popleft()
                self.queued_bytes -= len(frame)
                if isinstance(frame, str):
                    await self.send(text_data=frame)
                else:
                    await self.send(bytes_data=frame)
                frames += 1
                size += len(frame)
                if frames == 256:  # counted in runs: a counter per frame costs a busy topic ~10 %
                    prometheus.bridge_sent(self.kind, frames, size)
                    frames = size = 0
            if frames:
                prometheus.bridge_sent(self.kind, frames, size)
            self.wake.clear()
            await self.wake.wait()

    # ---------------------------------------------------------------- closing

    async def tell(self, text: str, level: str = "error") -> None:
        """Send the client a status in its protocol's own words."""
        if not self.closing:
            await self.send(text_data=status_frame(self.kind, text, level))

    async def end(self, reason: str, code: int) -> None:
        """Say why in the protocol's status, then close with a code and the reason."""
        if self.closing:
            return
        await self.tell(reason)
        self.closing = True
        await self.close(code, reason=reason[:120])

    async def disconnect(self, code: int) -> None:
        self.closing = True
        self.wake.set()
        if self.counted:
            prometheus.BRIDGE_CLIENTS.labels(self.kind).dec()
            self.counted = False
        if self.opened is not None:
            self.opened.cancel()
        if self.writer is not None:
            self.writer.cancel()
        if self.session and self.robot_channel and not self.session_closed:
            frame = bridge_envelope(Event.BRIDGE_CLOSE, {"session": self.session, "reason": "the client left"})
            goodbye = {"type": "robot.bridge", "session": self.session, "close": True, "frame": frame}
            await deliver(self.robot_channel, goodbye)
        if self.dropped:
            log.info("bridge client of %s left; %d frames dropped for it", self.robot_id, self.dropped)


class RosbridgeConsumer(BridgeConsumer):
    """A rosbridge v2 client (roslibpy, roslibjs) of one robot."""

    kind = "rosbridge"


class FoxgloveConsumer(BridgeConsumer):
    """A Foxglove WebSocket client (Foxglove, Lichtblick) of one robot."""

    kind = "foxglove"


class RobotBridges:
    """The bridge sessions on one robot's connection: which client channel each one answers to."""

    def __init__(self, robot_id: str) -> None:
        self.robot_id = robot_id
        self.clients: dict[str, str] = {}  # session -> the client consumer's channel
        self.kinds: dict[str, str] = {}  # session -> rosbridge or foxglove
        self.dropped = 0  # frames for clients whose channel was full, or naming a blob no longer here
        # The robot's latest blobs (frames several clients share), as the agent counts them.
        self.window = BlobWindow()
        self.blobs: dict[int, str | bytes] = {}
        self.blob_parts: list[bytes] = []  # the parts so far of the blob being received
        self.blob_id = 0
        self.blob_size = 0

    async def from_client(self, message: dict[str, Any], send_text: Any) -> None:
        """Pass a client's frame to the robot; an open records the session, a close forgets it."""
        session = message["session"]
        opening = message.get("open")
        if opening is not None:
            if len(self.clients) >= MAX_SESSIONS_PER_ROBOT:
                reason = f"robot {self.robot_id} has too many bridge clients"
                await deliver(opening, {"type": "bridge.closed", "reason": reason})
                return
            self.clients[session] = opening
            self.kinds[session] = message.get("kind", "rosbridge")
            await deliver(opening, {"type": "bridge.opened"})
        elif session not in self.clients:
            return  # a late frame of a session that ended
        if message.get("close"):
            self.clients.pop(session, None)
            self.kinds.pop(session, None)
        await send_text(message["frame"])

    def take_blob(self, message: bytes) -> None:
        """Keep a blob (or a part of one) the robot sent; ProtocolError if it is malformed."""
        blob, text, more, body = protocol.decode_bridge_blob(message)
        prometheus.BRIDGE_BLOB_BYTES.inc(len(body))
        if self.blob_parts and blob != self.blob_id:
            self.blob_parts, self.blob_size = [], 0
            raise protocol.ProtocolError(f"bridge blob {blob} began before blob {self.blob_id} ended")
        self.blob_id = blob
        self.blob_parts.append(body)
        self.blob_size += len(message)  # headers too: the agent's window counts the messages it sent
        if sum(map(len, self.blob_parts)) > protocol.BRIDGE_BLOB_MAX_BYTES:
            self.blob_parts, self.blob_size = [], 0
            raise protocol.ProtocolError(f"a bridge blob may carry at most {protocol.BRIDGE_BLOB_MAX_BYTES} bytes")
        if more:
            return
        parts, size = self.blob_parts, self.blob_size
        self.blob_parts, self.blob_size = [], 0
        data = parts[0] if len(parts) == 1 else b"".join(parts)
        for gone in self.window.add(blob, size):
            self.blobs.pop(gone, None)
        if text:
            try:
                self.blobs[blob] = data.decode("utf-8", "surrogatepass")
            except UnicodeDecodeError:
                self.blobs.pop(blob, None)
                raise protocol.ProtocolError("a text bridge blob is not UTF-8") from None
        else:
            self.blobs[blob] = data

    async def from_robot(self, event: str, payload: Any) -> None:
        """Pass a robot's bridge frame or close to its client."""
        channel = self.clients.get(payload.session)
        if channel is None:
            return
        if event == Event.BRIDGE_CLOSE:
            del self.clients[payload.session]
            self.kinds.pop(payload.session, None)
            await deliver(channel, {"type": "bridge.closed", "reason": payload.reason})
            return
        kind = self.kinds.get(payload.session, "rosbridge")
        if payload.dropped:
            prometheus.bridge_dropped(kind, "robot_queue", payload.dropped)
        if payload.blob is not None:
            message = self.blob_frame(payload)
            if message is None:
                return
        else:
            message = {"type": "bridge.frame", "data": payload.model_dump(exclude_none=True)}
        if not await deliver(channel, message):
            self.dropped += 1
            prometheus.bridge_dropped(kind, "channel_full")

    def blob_frame(self, payload: Any) -> dict[str, Any] | None:
        """Put a client's frame together from its head and a blob (None, counted, if the blob left)."""
        data = self.blobs.get(payload.blob)
        if data is None or (isinstance(data, str) and payload.head):
            # Pushed out of the window before this frame named it (the agent counts as we do, so
            # only a frame that was long in coming), or a head on a text frame: lost, counted.
            self.dropped += 1
            prometheus.bridge_dropped(self.kinds.get(payload.session, "rosbridge"), "blob_missing")
            return None
        if payload.head:
            data = base64.b64decode(payload.head) + data  # type: ignore[operator]
        return {"type": "bridge.frame", "whole": data}

    async def robot_left(self) -> None:
        """Tell every client the robot went offline."""
        clients, self.clients = self.clients, {}
        self.kinds.clear()
        self.window.clear()
        self.blobs.clear()
        self.blob_parts, self.blob_size = [], 0
        for channel in clients.values():
            await deliver(channel, {"type": "bridge.closed", "offline": True})
