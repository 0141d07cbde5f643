"""What the bridge protocols share: one graph subscription per topic feeding every client's own queue.

A topic is subscribed in the graph once, however many clients of however many protocols read it;
each client reads it through an ``Outlet``, a bounded queue that drops (and counts) its oldest
message when the client reads slower than the topic runs, so a slow client never holds up the
robot or another client. Clients that publish a topic share one publisher of it in the graph.
"""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Awaitable, Callable
from typing import Protocol

from bridgeos_agent.bridges.graph import BridgeError, BridgeGraph, GraphPublisher, GraphSubscription, Sample

__all__ = [
    "BATCH_FRAMES",
    "DEFAULT_QUEUE",
    "LINGER_S",
    "Fanouts",
    "Outlet",
    "Publishers",
    "Reader",
    "Send",
    "SendMany",
    "SharedTail",
    "one_by_one",
]

DEFAULT_QUEUE = 100  # messages queued per topic for a client that reads slower than the topic runs
LINGER_S = 5.0  # how long a topic stays subscribed in the graph after its last client left
BATCH_FRAMES = 64  # frames a client's writer hands its door in one go at most

Send = Callable[[str | bytes], Awaitable[None]]
SendMany = Callable[[list[str | bytes]], Awaitable[None]]


def one_by_one(send: Send) -> SendMany:
    """Return a sender of several frames for a door that takes them one at a time."""

    async def send_many(frames: list[str | bytes]) -> None:
        for frame in frames:
            await send(frame)

    return send_many


class SharedTail(bytes):
    """A client's binary frame: a head of its own, then a message's bytes that other clients' frames share.

    It is the whole frame, as bytes; a door that can (the cloud relay) sends ``tail`` once for every
    client of the message and only each client's ``head`` besides.
    """

    head: bytes
    tail: bytes | memoryview

    def __new__(cls, head: bytes, tail: bytes | memoryview) -> SharedTail:
        frame = super().__new__(cls, b"".join((head, tail)))
        frame.head = head
        frame.tail = tail
        return frame


class Reader(Protocol):
    """A client's writer, told when one of its outlets has something to send."""

    def wake(self) -> None:
        """Note that an outlet has a message waiting."""


class Outlet:
    """What one client receives of one topic: a bounded queue, its messages sent and dropped."""

    __slots__ = ("dropped", "queue", "sent", "topic", "type")

    def __init__(self, topic: str, size: int = DEFAULT_QUEUE) -> None:
        self.topic = topic
        self.type = ""
        self.queue: deque[Sample] = deque(maxlen=size)
        self.dropped = 0
        self.sent = 0

    def offer(self, sample: Sample) -> None:
        """Queue a message, dropping (and counting) the oldest when the queue is full."""
        if len(self.queue) == self.queue.maxlen:
            self.dropped += 1
        self.queue.append(sample)

    def resize(self, size: int) -> None:
        """Hold at most ``size`` messages from now on (the newest are kept)."""
        if size != self.queue.maxlen:
            self.queue = deque(self.queue, maxlen=size)


class _Fanout:
    """One graph subscription and the outlets it feeds."""

    __slots__ = ("idle", "outlets", "subscription")

    def __init__(self) -> None:
        self.subscription: GraphSubscription | None = None
        self.outlets: dict[Outlet, Reader] = {}
        self.idle: asyncio.TimerHandle | None = None  # the unsubscribe pending once the last client left

    def deliver(self, sample: Sample) -> None:
        for outlet, reader in self.outlets.items():
            outlet.offer(sample)
            reader.wake()


class Fanouts:
    """The graph subscriptions of one bridge, each shared by every client of its topic."""

    def __init__(self, graph: BridgeGraph, *, linger_s: float = LINGER_S) -> None:
        self.graph = graph
        self.linger_s = linger_s
        self._fanouts: dict[str, _Fanout] = {}
        self._attaching: dict[str, asyncio.Lock] = {}

    async def attach(self, topic: str, type_: str | None, outlet: Outlet, reader: Reader) -> str:
        """Feed ``outlet`` with a topic, subscribing in the graph for its first client; return its type."""
        lock = self._attaching.setdefault(topic, asyncio.Lock())
        async with lock:
            fanout = self._fanouts.get(topic)
            if fanout is None:
                fanout = _Fanout()
                fanout.subscription = await self.graph.subscribe(topic, type_, fanout.deliver)
                self._fanouts[topic] = fanout
            assert fanout.subscription is not None
            if fanout.idle is not None:
                fanout.idle.cancel()
                fanout.idle = None
            if type_ is not None and self.graph.normalize_type(type_) != fanout.subscription.type:
                if not fanout.outlets:
                    self._drop(topic)
                raise BridgeError(f"{topic} is of type {fanout.subscription.type}, not {type_}")
            fanout.outlets[outlet] = reader
            outlet.type = fanout.subscription.type
            return fanout.subscription.type

    def detach(self, topic: str, outlet: Outlet) -> None:
        """Stop feeding an outlet; the graph subscription ends a little after the last one leaves."""
        fanout = self._fanouts.get(topic)
        if fanout is not None:
            fanout.outlets.pop(outlet, None)
            if not fanout.outlets and fanout.idle is None:
                # Kept a moment: a client that unsubscribes and subscribes again (page reloads, roslibjs
                # re-subscribing) reuses the connection instead of racing a publisher's teardown of it.
                fanout.idle = asyncio.get_running_loop().call_later(self.linger_s, self._expire, topic, fanout)

    def _expire(self, topic: str, fanout: _Fanout) -> None:
        if self._fanouts.get(topic) is fanout and not fanout.outlets:
            self._drop(topic)

    def _drop(self, topic: str) -> None:
        fanout = self._fanouts.pop(topic)
        if fanout.idle is not None:
            fanout.idle.cancel()
        if fanout.subscription is not None:
            fanout.subscription.close()

    def topics(self) -> list[str]:
        """Return the topics subscribed in the graph."""
        return list(self._fanouts)

    def close(self) -> None:
        """Leave every topic."""
        for topic in list(self._fanouts):
            self._drop(topic)


class Publishers:
    """The graph publishers of one bridge, each shared by every client publishing its topic."""

    def __init__(self, graph: BridgeGraph) -> None:
        self.graph = graph
        self._publishers: dict[str, tuple[GraphPublisher, set[object]]] = {}

    async def advertise(self, topic: str, type_: str, user: object) -> GraphPublisher:
        """Publish on a topic for a client; refuse a type other than the topic's."""
        entry = self._publishers.get(topic)
        if entry is None:
            known = (await self.graph.topics()).get(topic)
            wanted = self.graph.normalize_type(type_)
            if known is not None and known != wanted:
                raise BridgeError(f"{topic} already exists with type {known}, not {type_}")
            entry = (await self.graph.advertise(topic, wanted), set())
            self._publishers[topic] = entry
        publisher, users = entry
        if self.graph.normalize_type(type_) != publisher.type:
            raise BridgeError(f"{topic} is advertised with type {publisher.type}, not {type_}")
        users.add(user)
        return publisher

    def unadvertise(self, topic: str, user: object) -> None:
        """Forget a client's publisher; the last one leaving stops publishing in the graph."""
        entry = self._publishers.get(topic)
        if entry is not None:
            entry[1].discard(user)
            if not entry[1]:
                del self._publishers[topic]
                entry[0].close()
