"""A WebSocket link to the cloud speaking the bridgeOS protocol: authenticate, send, ack, receive."""

from __future__ import annotations

import asyncio
import contextlib
import ssl
import time
from collections.abc import Mapping
from typing import Any

import websockets

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Dedup, Envelope, Event, Payload, Reliable


class AuthenticationError(RuntimeError):
    """The cloud refused the link's credentials."""


class Link:
    """One authenticated connection: reliable sends, acks for what it receives, replies by id.

    It is the robot side of the protocol over a real socket, used by the Robot Controller
    and by tests that play a robot (or a client) against a real cloud.
    """

    def __init__(self, url: str, *, auto_ack: bool = True, ssl_context: ssl.SSLContext | None = None) -> None:
        self.url = url
        self.ssl_context = ssl_context  # for wss:// to a cloud whose CA is not the system's
        self.auto_ack = auto_ack
        self.reliable = Reliable()
        self.dedup = Dedup()
        self.inbox: asyncio.Queue[Envelope] = asyncio.Queue()
        self.waiters: dict[str, asyncio.Future[Envelope]] = {}
        self.acked: dict[str, asyncio.Event] = {}
        self.ws: Any = None
        self._reader: asyncio.Task | None = None
        self._resender: asyncio.Task | None = None
        self.closed = asyncio.Event()
        self.refused: list[protocol.ProtocolError] = []
        self.close_code: int | None = None

    async def connect(
        self, event: Event, credentials: Mapping[str, Any], *, headers: Mapping[str, str] | None = None
    ) -> Envelope:
        """Open the socket and authenticate; return the authentication_success frame."""
        options: dict[str, Any] = {"ssl": self.ssl_context} if self.ssl_context is not None else {}
        self.ws = await websockets.connect(
            self.url, additional_headers=headers, max_size=2**21, open_timeout=10, **options
        )
        request = protocol.make(event, dict(credentials), now=time.time())
        await self.ws.send(protocol.encode(request))
        answer = protocol.decode(await asyncio.wait_for(self.ws.recv(), 10))
        if answer.event != Event.AUTHENTICATION_SUCCESS:
            await self.ws.close()
            raise AuthenticationError(getattr(protocol.parse_payload(answer), "reason", answer.event))
        self._reader = asyncio.create_task(self._read())
        self._resender = asyncio.create_task(self._resend())
        return answer

    async def send(self, event: Event | str, data: Payload | Mapping[str, Any] | None = None, **kw: Any) -> Envelope:
        """Send a frame; state-changing frames are resent until the cloud acks them."""
        envelope = protocol.make(event, data, now=time.time(), **kw)
        await self.send_envelope(envelope)
        return envelope

    async def send_envelope(self, envelope: Envelope) -> None:
        """Send an already built frame, tracking it for acks when it needs one."""
        if envelope.event in protocol.REQUIRES_ACK:
            self.reliable.send(envelope, time.monotonic())
            self.acked.setdefault(envelope.id, asyncio.Event())
        await self.ws.send(protocol.encode(envelope))

    async def request(
        self, event: Event | str, data: Mapping[str, Any] | None = None, *, timeout: float = 10
    ) -> Envelope:
        """Send a frame and wait for the frame that answers it."""
        envelope = protocol.make(event, data, now=time.time())
        future: asyncio.Future[Envelope] = asyncio.get_running_loop().create_future()
        self.waiters[envelope.id] = future
        try:
            await self.send_envelope(envelope)
            return await asyncio.wait_for(future, timeout)
        finally:
            self.waiters.pop(envelope.id, None)

    async def wait_acked(self, envelope: Envelope, timeout: float = 10) -> None:
        """Wait until the cloud acknowledged a frame."""
        await asyncio.wait_for(self.acked[envelope.id].wait(), timeout)

    async def next(self, *events: str, timeout: float = 10) -> Envelope:
        """Return the next received frame of one of these events (any event if none given)."""
        async with asyncio.timeout(timeout):
            while True:
                envelope = await self.inbox.get()
                if not events or envelope.event in events:
                    return envelope

    async def _read(self) -> None:
        try:
            async for raw in self.ws:
                try:
                    envelope = protocol.decode(raw)
                except protocol.ProtocolError as exc:
                    # One bad frame from the peer must not stop the link; keep it for inspection.
                    self.refused.append(exc)
                    continue
                if envelope.reply_to and envelope.event == Event.ACK and self.reliable.on_ack(envelope.reply_to):
                    self.acked[envelope.reply_to].set()
                waiter = self.waiters.get(envelope.reply_to) if envelope.reply_to else None
                if waiter is not None and not waiter.done():
                    waiter.set_result(envelope)
                if envelope.event in protocol.REQUIRES_ACK and self.auto_ack:
                    await self.ws.send(protocol.encode(protocol.ack_frame(envelope.id, now=time.time())))
                    if self.dedup.seen(envelope.id):
                        continue
                if envelope.event != Event.ACK:
                    self.inbox.put_nowait(envelope)
        except websockets.ConnectionClosed:
            pass
        finally:
            self.close_code = self.ws.close_code
            self.closed.set()

    async def _resend(self) -> None:
        while True:
            await asyncio.sleep(0.2)
            for envelope in self.reliable.due(time.monotonic()):
                with contextlib.suppress(websockets.ConnectionClosed):
                    await self.ws.send(protocol.encode(envelope))

    async def close(self) -> None:
        """Close the socket and stop the link's tasks."""
        for task in (self._resender, self._reader):
            if task is not None:
                task.cancel()
        if self.ws is not None:
            await self.ws.close()
