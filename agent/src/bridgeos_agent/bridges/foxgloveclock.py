"""The Foxglove WebSocket ``time`` capability: the graph's simulated clock, told to clients that were offered it.

The protocol's time frames exist for time that is not the wall clock ("accelerated, slowed, or
stepped"), and a server that sends them must stamp its messages from the same source. So the
capability is offered only while the graph runs on simulated time (ROS 1's ``/use_sim_time``, or
someone publishing ``/clock`` on ROS 2): then ``/clock`` is followed, its time goes to the clients
at most every ``interval_s`` (the latest value; a slow client never queues old ones), and their
messages are stamped with it. On wall-clock time nothing changes: no capability, wall stamps.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

from bridgeos_agent.bridges.graph import BridgeError, BridgeGraph, GraphSubscription, Sample

__all__ = ["CAPABILITY", "INTERVAL_S", "SimClock"]

logger = logging.getLogger(__name__)

CAPABILITY = "time"
INTERVAL_S = 0.05  # time frames go out at most this often (a simulator may publish /clock at 1 kHz)
CLOCK = ("/clock", "rosgraph_msgs/Clock")


def clock_ns(msg: dict[str, Any]) -> int:
    """Return a rosgraph_msgs/Clock message's time in nanoseconds (ROS 1's secs/nsecs or ROS 2's sec/nanosec)."""
    stamp = msg["clock"]
    seconds = stamp.get("sec", stamp.get("secs", 0))
    nanoseconds = stamp.get("nanosec", stamp.get("nsecs", 0))
    return int(seconds) * 1_000_000_000 + int(nanoseconds)


class SimClock:
    """Follow the graph's /clock while it runs on simulated time, and tell the time to whoever listens."""

    def __init__(self, graph: BridgeGraph, tell: Callable[[int], None], interval_s: float = INTERVAL_S) -> None:
        self.graph = graph
        self.tell = tell  # called with the latest time (ns) at most every interval_s
        self.interval_s = interval_s
        self.active = False
        self.now_ns: int | None = None
        self._subscription: GraphSubscription | None = None
        self._told_at = 0.0
        self._pending: asyncio.TimerHandle | None = None

    async def check(self) -> bool:
        """Look whether the graph runs on simulated time now; follow /clock while it does."""
        try:
            simulated = await self.graph.simulated_clock()
        except BridgeError as exc:
            logger.debug("foxglove: cannot tell the graph's clock: %s", exc)
            return self.active
        if simulated and self._subscription is None:
            try:
                self._subscription = await self.graph.subscribe(CLOCK[0], _clock_type(self.graph), self._heard)
            except BridgeError as exc:
                logger.warning("foxglove: the graph runs on simulated time but /clock cannot be read: %s", exc)
                return self.active
        elif not simulated and self._subscription is not None:
            self.close()
        self.active = simulated
        return simulated

    def stamp(self, sample: Sample) -> int:
        """Return a message's timestamp in nanoseconds from the simulated clock (its arrival, before any /clock)."""
        if self.now_ns is not None:
            # The latest /clock when the message goes out: within a writer's wait of its arrival.
            return self.now_ns
        seconds, nanoseconds = sample.stamp
        return seconds * 1_000_000_000 + nanoseconds

    def _heard(self, sample: Sample) -> None:
        try:
            self.now_ns = clock_ns(sample.msg())
        except (BridgeError, KeyError, TypeError, ValueError) as exc:
            logger.debug("foxglove: a /clock message does not read: %s", exc)
            return
        if self._pending is not None:
            return
        wait = self._told_at + self.interval_s - time.monotonic()
        if wait <= 0:
            self._flush()
        else:
            self._pending = asyncio.get_running_loop().call_later(wait, self._flush)

    def _flush(self) -> None:
        self._pending = None
        self._told_at = time.monotonic()
        if self.now_ns is not None:
            self.tell(self.now_ns)

    def close(self) -> None:
        """Stop following /clock."""
        if self._pending is not None:
            self._pending.cancel()
            self._pending = None
        if self._subscription is not None:
            with contextlib.suppress(Exception):
                self._subscription.close()
            self._subscription = None
        self.now_ns = None
        self.active = False


def _clock_type(graph: BridgeGraph) -> str:
    return graph.normalize_type(CLOCK[1])
