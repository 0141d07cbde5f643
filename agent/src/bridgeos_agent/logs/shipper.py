"""Ship the rings' new lines to the cloud: last in line, under a per-robot cap, resent from the cursor.

A ``component_logs`` frame is never written to the outbox: its lines are in the ring, so it is
sent once and, if the link drops or the cloud does not ack it in time, built again from the
ring's shipped-up-to cursor (the cloud stores a seq once). At most ``in_flight`` frames wait
for their ack; a frame goes only when the socket holds nothing else to send (metrics, commands
and state go first) and the token bucket of lines and bytes allows it. Lines the ring
overwrote before they went are counted in the next frame's ``dropped``.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import itertools
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from bridgeos_agent import protocol
from bridgeos_agent.logs.ring import LogRing, RingLine, Rings
from bridgeos_agent.protocol import ComponentLogs, Event

if TYPE_CHECKING:
    from bridgeos_agent.session import Session

__all__ = ["LogShipper", "TokenBucket", "encode_frame", "frame_data"]

logger = logging.getLogger("bridgeos_agent")

FRAME_BYTES = 512 * 1024  # a frame's size at most: well under MAX_FRAME_BYTES, and short on a slow link
SOCKET_BUFFERED = 64 * 1024  # a log frame waits while the socket holds more than this unsent
ACK_TIMEOUT = 30.0
RETRY_CODES = frozenset({"unavailable", "internal_error", "rate_limited"})
REFUSED_CODES = frozenset({"unsupported", "unknown_event", "forbidden_event"})  # a cloud without logs


class TokenBucket:
    """Allow ``rate`` units a second with bursts of one second's worth; taking more leaves a debt."""

    def __init__(self, rate: float, clock: Callable[[], float] = time.monotonic) -> None:
        self.rate = float(rate)
        self.clock = clock
        self.tokens = float(rate)
        self._at = clock()

    def available(self) -> float:
        """Return the units available now."""
        now = self.clock()
        self.tokens = min(self.rate, self.tokens + (now - self._at) * self.rate)
        self._at = now
        return self.tokens

    def take(self, amount: float) -> None:
        """Spend ``amount`` units (going into debt if there are fewer)."""
        self.available()
        self.tokens -= amount

    def wait(self, amount: float) -> float:
        """Return the seconds until ``amount`` units (at most a burst) are available."""
        missing = min(amount, self.rate) - self.available()
        return max(0.0, missing / self.rate) if self.rate > 0 else 1.0

    def set_rate(self, rate: float) -> None:
        """Use a new rate from now on."""
        self.available()
        self.rate = float(rate)
        self.tokens = min(self.tokens, self.rate)


def frame_data(skill: str, component: str, lines: list[RingLine], dropped: int = 0) -> dict[str, Any]:
    """Return the data of a ``component_logs`` frame carrying ring lines."""
    return {
        "skill": skill,
        "component": component,
        "location": "robot",
        "lines": [
            {"seq": seq, "ts": ts, "stream": stream, "level": level, "text": text}
            for seq, ts, stream, level, text in lines
        ],
        "dropped": dropped,
    }


def encode_frame(data: dict[str, Any], *, now: float) -> tuple[str, str]:
    """Validate a ``component_logs`` payload and encode its frame; return (frame id, text).

    The payload is validated as ``protocol.make`` would; the envelope around it is written
    directly (as ``protocol.ack_text`` does), which halves the cost of a 5,000-line frame.
    """
    payload = ComponentLogs.model_validate(data)
    frame_id = protocol.new_id()
    body = payload.model_dump_json(exclude_none=True)
    return frame_id, f'{{"event":"{Event.COMPONENT_LOGS.value}","id":"{frame_id}","data":{body},"ts":{float(now)!r}}}'


@dataclass(slots=True)
class _Sent:
    """A frame waiting for its ack: the seq it ends at, how many lines it carries and dropped."""

    frame_id: str
    last: int
    lines: int
    dropped: int
    acked: bool = False


@dataclass(slots=True)
class _Flow:
    """What the shipper knows of one ring: sent up to, and its frames in flight in order."""

    key: tuple[str, str]
    ring: LogRing
    sending: int  # lines up to this seq are sent (or acked)
    frames: list[_Sent] = field(default_factory=list)


class LogShipper:
    """Send the rings' lines to the cloud through the robot's session, lowest priority."""

    def __init__(
        self,
        rings: Rings,
        session: Session,
        *,
        lines_per_s: float,
        bytes_per_s: float,
        in_flight: int = 2,
        ack_timeout: float = ACK_TIMEOUT,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.rings = rings
        self.session = session
        self.lines = TokenBucket(lines_per_s, clock)
        self.bytes = TokenBucket(bytes_per_s, clock)
        self.in_flight = in_flight
        self.ack_timeout = ack_timeout
        self.clock = clock
        self.enabled = True
        self.shipped_lines = 0  # acked by the cloud
        self.dropped_lines = 0  # never shipped: overwritten in the ring first
        self.frames_sent = 0
        self.wake = asyncio.Event()  # set when lines were appended or a frame was answered
        self._flows: dict[tuple[str, str], _Flow] = {}
        self._sent: dict[str, tuple[_Flow, float]] = {}  # frames in flight: id -> (their ring's flow, sent at)
        self._turn = itertools.count()
        self._refused = False  # the cloud does not take component logs: not sent again on this link

    # --- the loop -------------------------------------------------------------------------

    async def run(self) -> None:
        """Ship for as long as the agent runs."""
        while True:
            delay = await self.ship_once()
            if delay:
                self.wake.clear()
                # asyncio.timeout, not wait_for: Python 3.11's wait_for can swallow a cancellation
                # that comes as the wait ends, and the loop would outlive its owner's close.
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(delay):
                        await self.wake.wait()

    async def ship_once(self) -> float:
        """Send one frame if one may go now; return how long to wait before trying again (0: at once)."""
        self._expire()
        if not self.enabled or self._refused or len(self._sent) >= self.in_flight:
            return 0.5 if self._refused or not self.enabled else 0.1
        if not self.session.idle(SOCKET_BUFFERED):
            return 0.02 if self.session.ws is not None else 0.25  # other frames first, or no link
        flow = self._next_flow()
        if flow is None:
            return 0.25
        pending = flow.ring.seq - flow.sending
        wanted = min(pending, protocol.MAX_LOG_LINES_PER_FRAME, max(1, int(self.lines.rate // 5)))
        byte_floor = min(FRAME_BYTES, max(1024.0, self.bytes.rate / 5))
        wait = max(self.lines.wait(wanted), self.bytes.wait(byte_floor))
        if wait > 0:
            return min(wait, 0.5)
        limit = max(1, min(wanted, int(self.lines.available())))
        budget = int(min(FRAME_BYTES, max(byte_floor, self.bytes.available())))
        start = flow.sending
        built = await asyncio.to_thread(self._build, flow, limit, budget)
        if built is None:
            return 0.05  # the ring was emptied meanwhile (made smaller): looked at again shortly
        if flow.sending != start:
            return 0.0  # the frames before it were lost meanwhile (the link dropped): sent again from the cursor
        frame_id, text, last, count, dropped = built
        self.lines.take(count)
        self.bytes.take(len(text))
        # Noted before the send: an answer cannot come sooner, but the link may drop during it.
        self._sent[frame_id] = (flow, self.clock())
        flow.frames.append(_Sent(frame_id=frame_id, last=last, lines=count, dropped=dropped))
        flow.sending = last
        if not await self.session.send_unkept(frame_id, text, functools.partial(self._answered, frame_id)):
            self._lost(flow)
            return 0.1
        self.frames_sent += 1
        return 0.0

    def _next_flow(self) -> _Flow | None:
        """Return the next ring with lines to send, taking turns so no component starves the others."""
        rings = self.rings.known()
        if not rings:
            return None
        start = next(self._turn) % len(rings)
        for key, ring in rings[start:] + rings[:start]:
            flow = self._flows.get(key)
            if flow is None or flow.ring is not ring:
                flow = self._flows[key] = _Flow(key=key, ring=ring, sending=ring.shipped)
            if ring.seq > flow.sending:
                return flow
        return None

    def _build(self, flow: _Flow, limit: int, budget: int) -> tuple[str, str, int, int, int] | None:
        """Read and encode a frame of a ring's next lines (in a thread: thousands of lines)."""
        skill, component = flow.key
        while True:
            lines = flow.ring.lines_after(flow.sending, limit, budget)
            if not lines:
                return None
            # A frame ends before a gap in the seqs (lines passed over unread): the next one counts it dropped.
            for index in range(1, len(lines)):
                if lines[index][0] != lines[index - 1][0] + 1:
                    lines = lines[:index]
                    break
            # Lines between the cursor and the ring's oldest were overwritten before they went.
            dropped = max(0, lines[0][0] - flow.sending - 1)
            frame_id, text = encode_frame(frame_data(skill, component, lines, dropped), now=time.time())
            if len(lines) == 1 or len(text.encode("utf-8", "surrogatepass")) <= protocol.MAX_FRAME_BYTES - 1024:
                return frame_id, text, lines[-1][0], len(lines), dropped
            limit = max(1, len(lines) // 2)  # escaping made it bigger than estimated

    # --- answers --------------------------------------------------------------------------

    def _answered(self, frame_id: str, code: str | None) -> None:
        """Take the cloud's answer to a frame: acked moves the cursor; lost or refused for now, sent again."""
        found = self._sent.pop(frame_id, None)
        self.wake.set()
        if found is None:
            return  # given up on already (no ack in time): its lines are sent again anyway
        flow = found[0]
        if code in REFUSED_CODES:
            self._refused = True
            logger.warning("the cloud does not take component logs (%s): not sent again on this link", code)
        elif code is not None and code not in RETRY_CODES and code != "disconnected":
            logger.warning("the cloud refused a component_logs frame (%s): its lines are skipped", code)
            code = None
        if code is not None:
            self._lost(flow)
            return
        for sent in flow.frames:
            if sent.frame_id == frame_id:
                sent.acked = True
        while flow.frames and flow.frames[0].acked:
            sent = flow.frames.pop(0)
            flow.ring.mark_shipped(sent.last)
            self.shipped_lines += sent.lines
            self.dropped_lines += sent.dropped

    def _lost(self, flow: _Flow) -> None:
        """Send a ring's frames in flight again from its cursor (the link dropped, or no ack came)."""
        for sent in flow.frames:
            if self._sent.pop(sent.frame_id, None) is not None:
                self.session.forget_unkept(sent.frame_id)
        flow.frames.clear()
        flow.sending = flow.ring.shipped

    def _expire(self) -> None:
        now = self.clock()
        for flow, at in list(self._sent.values()):
            if now - at > self.ack_timeout:
                self._lost(flow)

    def on_disconnect(self) -> None:
        """Allow a cloud that refused logs another try on the next link."""
        self._refused = False
