"""What both WebSocket doors share: authentication first, envelopes, errors, rate limits."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Awaitable, Callable
from typing import Any

from autobahn.exception import Disconnected
from channels.consumer import get_handler_name
from channels.generic.websocket import AsyncWebsocketConsumer
from django.core.exceptions import ValidationError

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Direction, Envelope, Event, ProtocolError

from .ratelimit import TokenBucket

# A socket must send its credentials this soon after it is accepted. In a connect storm of thousands
# the first frames queue behind each other in the one loop (10 s refused 6 of 10,000 robots here),
# so as long as daphne lets a handshake wait (scripts/daphne) and the agent waits for its answer.
AUTH_TIMEOUT = 30.0
# Closed after this many frames refused by the rate limit with no quiet second between: abuse.
MAX_FLOOD_STRIKES = 500
FLOOD_QUIET_S = 1.0
CLOSE_AUTH_FAILED = 4001
CLOSE_FLOODING = 4008
CLOSE_TOO_MANY_FAILURES = 4029


def peek_id(raw: str | bytes | None) -> str | None:
    """Return the id of a frame that failed validation, to answer it; only on the error path."""
    try:
        frame = json.loads(raw) if raw else None
    except (ValueError, TypeError, RecursionError):
        return None
    frame_id = frame.get("id") if isinstance(frame, dict) else None
    return frame_id if protocol.is_valid_id(frame_id) else None


def validation_message(exc: ValidationError) -> tuple[str, str | None]:
    """Flatten a Django field error into one message and the field it names."""
    for field, messages in getattr(exc, "message_dict", {"": exc.messages}).items():
        return "; ".join(messages), f"data.{field}" if field else None
    return "invalid data", None


class ProtocolConsumer(AsyncWebsocketConsumer):
    """A socket speaking the bridgeOS protocol.

    Subclasses define ``authenticate(envelope) -> bool`` (check the first frame's credentials,
    set the connection up, answer; False means it refused them) and ``handle_frame(envelope)``.
    """

    direction: Direction
    auth_event: Event
    rate_setting: tuple[float, float]

    async def dispatch(self, message: dict[str, Any]) -> None:
        """Call the handler of a message, without Channels' per-message hop to a thread.

        Channels closes stale database connections in a worker thread before every message,
        which halves a busy consumer's frame rate; these consumers reach the database only
        through database_sync_to_async, which does that cleanup itself around each call.
        """
        handler = getattr(self, get_handler_name(message), None)
        if handler is None:
            raise ValueError(f"no handler for message type {message['type']}")
        await handler(message)

    async def connect(self) -> None:
        self.authenticated = False
        self.closing = False
        self.tasks: set[asyncio.Task] = set()
        rate, burst = self.rate_setting
        self.bucket = TokenBucket(rate, burst, time.monotonic())
        self.flood_strikes = 0
        self.last_refused = 0.0
        await self.accept()
        self.auth_timer = asyncio.get_running_loop().call_later(
            AUTH_TIMEOUT, self.spawn_call, self.refuse, "authentication timed out"
        )

    async def closed(self, code: int) -> None:
        """Clean up after the socket closed."""

    # ---------------------------------------------------------------- sending

    async def send_envelope(self, envelope: Envelope) -> None:
        """Send one frame to the peer."""
        await self.send_text(protocol.encode(envelope))

    async def send_text(self, text: str) -> None:
        """Send one already encoded frame, unless the socket is closing."""
        if not self.closing:
            try:
                await self.send(text_data=text)
            except Disconnected:
                # The peer went away between our check and the write; disconnect() follows.
                self.closing = True

    async def answer(self, request: Envelope, event: Event, data: dict[str, Any]) -> None:
        """Answer a request of the peer."""
        await self.send_envelope(protocol.make(event, data, reply_to=request.id, now=time.time()))

    async def ack(self, envelope: Envelope) -> None:
        """Acknowledge a frame."""
        await self.send_text(protocol.ack_text(envelope.id, now=time.time()))

    async def fail(self, message: str, *, reply_to: str | None, field: str | None = None, code: str) -> None:
        """Tell the peer a frame was refused, and why."""
        payload = {"message": message[:2000], "code": code}
        if field:
            payload["field"] = field
        await self.send_envelope(protocol.make(Event.ERROR_MESSAGE, payload, reply_to=reply_to, now=time.time()))

    def spawn(self, coroutine: Awaitable[Any]) -> asyncio.Future:
        """Run a coroutine owned by this connection: cancelled when it closes."""
        task = asyncio.ensure_future(coroutine)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    def spawn_call(self, function: Callable[..., Awaitable[Any]], *args: Any) -> None:
        """Spawn ``function(*args)``; for timer callbacks."""
        self.spawn(function(*args))

    # ---------------------------------------------------------------- receiving

    async def receive(self, text_data: str | None = None, bytes_data: bytes | None = None) -> None:
        raw = text_data if text_data is not None else bytes_data
        if self.closing:
            return
        if not self.authenticated:
            await self.first_frame(raw)
            return
        now = time.monotonic()
        if not self.bucket.allow(now):
            await self.flooded(raw, now)
            return
        try:
            envelope = protocol.decode(raw, direction=self.direction)
        except ProtocolError as exc:
            await self.fail(exc.message, reply_to=peek_id(raw), field=exc.field, code=exc.code)
            return
        await self.handle_frame(envelope)

    async def first_frame(self, raw: str | bytes | None) -> None:
        """Accept the first frame only if it is valid credentials."""
        self.auth_timer.cancel()
        expected = f"first frame must be {self.auth_event}"
        try:
            envelope = protocol.decode(raw, direction=self.direction)
        except ProtocolError as exc:
            await self.refuse(f"{expected} ({exc})", reply_to=peek_id(raw))
            return
        if envelope.event != self.auth_event:
            await self.refuse(expected, reply_to=envelope.id)
            return
        self.authenticated = await self.authenticate(envelope)

    async def flooded(self, raw: str | bytes | None, now: float) -> None:
        """Refuse a frame over the rate limit; close the connection if the flood goes on."""
        if now - self.last_refused > FLOOD_QUIET_S:
            self.flood_strikes = 0
        self.last_refused = now
        self.flood_strikes += 1
        if self.flood_strikes >= MAX_FLOOD_STRIKES:
            await self.fail("too many frames, closing", reply_to=None, code="rate_limited")
            await self.close_with(CLOSE_FLOODING, "flooding")
            return
        # Not acked, so a robot keeps the frame and sends it again later: nothing is lost.
        await self.fail("rate limit exceeded, send again later", reply_to=peek_id(raw), code="rate_limited")

    # ---------------------------------------------------------------- closing

    async def refuse(self, reason: str, reply_to: str | None = None, code: int = CLOSE_AUTH_FAILED) -> None:
        """Answer authentication_failure and close (4001, or 4029 after too many failures)."""
        if self.closing:
            return
        frame = protocol.make(
            Event.AUTHENTICATION_FAILURE, {"reason": reason[:500]}, reply_to=reply_to, now=time.time()
        )
        await self.send_envelope(frame)
        await self.close_with(code, "authentication failed")

    async def close_with(self, code: int, reason: str) -> None:
        """Close the socket once, remembering why."""
        if not self.closing:
            self.closing = True
            self.close_reason = reason
            await self.close(code)

    async def disconnect(self, code: int) -> None:
        self.closing = True
        self.auth_timer.cancel()
        for task in self.tasks:
            task.cancel()
        await self.closed(code)
