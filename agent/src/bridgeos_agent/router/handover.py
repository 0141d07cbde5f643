"""Exact handovers between two relays: which relay delivers a (topic, subscriber) pair, and from where.

One relay is responsible for each pair at any moment. A handover is exact: the relay giving a
pair stops in one step of its event loop and names the last message it delivered by the
fingerprints of the last few frames it saw (``FrameLog``); the relay taking it delivers from the
next one, out of its own log of the same stream (or as soon as the cut point arrives). A pair
whose publisher changes in the handover starts afresh with the new publisher, as a switch inside
one router does, once the old relay's queue to that subscriber has drained.

Limit: the cut point is found by content (length and CRC-32 of each frame's first and last
4 KiB, four frames in a row); a stream repeating four identical messages across a handover may
lose or repeat some of those identical messages.
"""

from __future__ import annotations

import asyncio
import logging
import time
import zlib
from collections import deque
from collections.abc import Iterable

from bridgeos_agent.rostopics import Publication, iter_frames
from bridgeos_agent.router.routes import Delivery, RoutedTopic
from bridgeos_agent.router.settings import Where

logger = logging.getLogger(__name__)

__all__ = ["AWAY", "HOLD", "Await", "FrameLog", "Gate", "cloud_pairs", "drained", "fingerprint", "start_after"]

ANCHOR = 4  # frames naming a cut point
LOG_FRAMES = 8192
LOG_BYTES = 64 << 20
QUIET_S = 0.05  # after a drain, before another relay writes to the same subscriber (its reader threads)

Pair = tuple[str, str]  # (canonical topic, subscriber component)


def fingerprint(frame: bytes) -> int:
    """Return a cheap, process-independent fingerprint of one frame (length and CRC of its ends)."""
    if len(frame) <= 8192:
        return (len(frame) << 32) | zlib.crc32(frame)
    return (len(frame) << 32) | zlib.crc32(frame[-4096:], zlib.crc32(frame[:4096]))


class FrameLog:
    """The recent frames of one topic's cloud source, fingerprinted, bounded in count and bytes."""

    __slots__ = ("bytes", "frames", "marks")

    def __init__(self) -> None:
        self.frames: deque[bytes] = deque()
        self.marks: deque[int] = deque()
        self.bytes = 0

    def add(self, blob: bytes, count: int) -> None:
        """Log a burst of frames."""
        for frame in (blob,) if count == 1 else iter_frames(blob):
            self.frames.append(frame)
            self.marks.append(fingerprint(frame))
            self.bytes += len(frame)
        while len(self.frames) > LOG_FRAMES or (self.bytes > LOG_BYTES and len(self.frames) > 1):
            self.bytes -= len(self.frames.popleft())
            self.marks.popleft()

    def clear(self) -> None:
        self.frames.clear()
        self.marks.clear()
        self.bytes = 0

    def anchor(self) -> list[int] | None:
        """Name the newest frame by the fingerprints of the last few (None when nothing was seen)."""
        if not self.marks:
            return None
        return list(self.marks)[-ANCHOR:]

    def after(self, anchor: list[int]) -> list[bytes] | None:
        """Return the frames logged after the cut point ``anchor`` names; None while it is not in the log."""
        marks = list(self.marks)
        size = len(anchor)
        for end in range(len(marks), 0, -1):
            # Near the log's start (it began inside the cut point's frames) a shorter match will do.
            if marks[max(0, end - size) : end] == anchor[max(0, size - end) :]:
                return list(self.frames)[end:]
        return None


def deliver_frames(topic: RoutedTopic, delivery: Delivery, where: str, source: str, frames: list[bytes]) -> int:
    """Send frames to one subscriber instance and count them as the hot path does; return those dropped."""
    if not frames:
        return 0
    blob = b"".join(frames)
    count = len(frames)
    payload = len(blob) - 4 * count
    publication: Publication = getattr(delivery, where)
    lost = publication.send(blob, count)
    delivery.messages += count - lost
    delivery.dropped += lost
    if where == "robot":
        topic.bytes_robot += payload
    else:
        topic.bytes_cloud += payload
    if source == "robot":
        delivery.bytes_robot += payload
    else:
        delivery.bytes_cloud += payload
    return lost


class Gate:
    """Why a router does not deliver a pair right now: handed to the other relay, or held."""

    __slots__ = ("name",)

    def __init__(self, name: str) -> None:
        self.name = name

    def burst(self, topic: RoutedTopic, delivery: Delivery, where: str, source: str, blob: bytes, count: int) -> int:
        return 0

    def __repr__(self) -> str:
        return f"<gate {self.name}>"


AWAY = Gate("away")  # the other relay delivers this pair
HOLD = Gate("hold")  # a handover to this relay is under way


class Await(Gate):
    """Deliver from the frame after a cut point, once the cut point is in the log."""

    __slots__ = ("anchor", "deadline", "what")

    def __init__(self, anchor: list[int], deadline: float, what: str) -> None:
        super().__init__("await")
        self.anchor = anchor
        self.deadline = deadline
        self.what = what

    def burst(self, topic: RoutedTopic, delivery: Delivery, where: str, source: str, blob: bytes, count: int) -> int:
        frames = topic.log.after(self.anchor) if topic.log is not None else None
        if frames is not None:
            delivery.gate = None
            return deliver_frames(topic, delivery, where, source, frames)
        if time.monotonic() < self.deadline:
            return 0
        logger.warning(
            "%s: the handover's cut point never arrived; delivering from now on (messages may be lost)", self.what
        )
        delivery.gate = None
        return deliver_frames(topic, delivery, where, source, list(iter_frames(blob)))


def start_after(topic: RoutedTopic, delivery: Delivery, where: str, anchor: list[int] | None, timeout: float) -> int:
    """Make a router deliver a pair from the frame after ``anchor`` (from the next one when None)."""
    if anchor is None:
        delivery.gate = None
        return 0
    frames = topic.log.after(anchor) if topic.log is not None else None
    if frames is None:
        delivery.gate = Await(anchor, time.monotonic() + timeout, f"{topic.canonical}")
        return 0
    delivery.gate = None
    return deliver_frames(topic, delivery, where, "cloud", frames)


def cloud_pairs(topics: Iterable[RoutedTopic], active: dict[str, Where | None]) -> set[Pair]:
    """Return the (topic, subscriber) pairs whose publisher and subscriber are both active in the cloud."""
    pairs = set()
    for topic in topics:
        if active.get(topic.route.publisher) != "cloud":
            continue
        for subscriber in topic.deliveries:
            if active.get(subscriber) == "cloud":
                pairs.add((topic.canonical, subscriber))
    return pairs


async def drained(publications: Iterable[Publication | None], timeout: float) -> None:
    """Wait until every subscriber connection of these publications has written what it was given."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        busy = [
            c
            for p in publications
            if p is not None
            for c in p.connections
            if c.backlog is not None or c.transport.get_write_buffer_size()
        ]
        if not busy:
            return
        await asyncio.sleep(0.005)
