"""Hold a Skill Router's routing table: routed topics and services, their counters, the shared state."""

from __future__ import annotations

import asyncio
import threading
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import aiohttp
from aiohttp import web

from bridgeos_agent.rosnames import canonical_name
from bridgeos_agent.rosnode import RosNode
from bridgeos_agent.rostopics import Publication
from bridgeos_agent.router.settings import RouterSettings, Where
from bridgeos_agent.skillconfig import HttpRoute, ServiceRoute, SkillConfig, TopicRoute

__all__ = ["Delivery", "RoutedService", "RoutedTopic", "RouterBase"]


class Delivery:
    """What one subscriber component of a topic received, split by where its source ran."""

    # "robot" and "cloud": the router's publication in that instance's namespace (slots, not a dict:
    # a router may map tens of thousands of topics).
    __slots__ = ("bytes_cloud", "bytes_robot", "cloud", "dropped", "gate", "messages", "robot")

    def __init__(self) -> None:
        self.robot: Publication | None = None
        self.cloud: Publication | None = None
        # None: this router delivers; else a cloudrelay.Gate says why not (yet): the pair is
        # handed to the other relay, or held until a handover's cut point arrives.
        self.gate: Any = None
        self.messages = 0
        self.dropped = 0
        self.bytes_robot = 0
        self.bytes_cloud = 0


class RoutedTopic:
    """One routed topic: its publications, the publisher's sources and its counters."""

    __slots__ = (
        "bytes_cloud",
        "bytes_robot",
        "canonical",
        "canonical_delivered",
        "canonical_pub",
        "deliveries",
        "dropped",
        "has_header",
        "last_age",
        "last_rate",
        "log",
        "messages",
        "node_pub",
        "outside_dropped",
        "outside_messages",
        "parked",
        "route",
        "store",
        "w_age_max",
        "w_age_n",
        "w_age_sq",
        "w_age_sum",
        "w_bytes",
        "w_dropped",
        "w_last",
        "w_messages",
        "w_period_max",
        "w_period_n",
        "w_period_sq",
        "w_period_sum",
        "w_start",
    )

    def __init__(self, route: TopicRoute, canonical_pub: Publication | None, now: float) -> None:
        self.route = route
        self.canonical = canonical_name(route.name)
        self.canonical_pub = canonical_pub
        self.deliveries: dict[str, Delivery] = {}
        self.store: deque[bytes] | None = deque(maxlen=route.store) if route.store else None
        self.has_header = False
        self.node_pub = ""
        self.log: Any = None  # handover.FrameLog of the cloud source's recent frames, when a cloud relay is linked
        self.parked = False  # a cloud relay delivering none of this topic: it only logs the frames
        self.last_rate = 0.0  # messages/s over the last statistics window
        self.last_age: float | None = None  # mean age of header.stamp then (s), when the type has a header
        # Totals since the router started (the publisher's side).
        self.messages = 0  # routed from the publisher's active instance
        self.outside_messages = 0  # routed from outside publishers on the canonical name
        self.canonical_delivered = 0  # sent to listeners of the canonical name
        self.dropped = 0  # of the publisher's messages, dropped on the way to a slow peer
        self.outside_dropped = 0
        self.bytes_robot = 0  # sent to peers on the robot (and outside nodes)
        self.bytes_cloud = 0
        self._reset_window(now)

    def _reset_window(self, now: float) -> None:
        """Start a new statistics window at ``now``."""
        self.w_start = now
        self.w_messages = 0
        self.w_bytes = 0
        self.w_dropped = 0
        self.w_last = 0.0
        self.w_period_n = 0  # messages with a period, its sum and sum of squares
        self.w_period_sum = 0.0
        self.w_period_sq = 0.0
        self.w_period_max = 0.0
        self.w_age_n = 0  # sampled header stamps: count, sum, sum of squares, max of their ages
        self.w_age_sum = 0.0
        self.w_age_sq = 0.0
        self.w_age_max = 0.0


class RoutedService:
    """One proxied service and its counters."""

    __slots__ = ("bytes", "calls", "canonical", "errors", "route")

    def __init__(self, route: ServiceRoute) -> None:
        self.route = route
        self.canonical = canonical_name(route.name)
        self.calls = 0
        self.bytes = 0
        self.errors = 0


class RouterBase:
    """Declare the state the parts of a Skill Router share (topics, services, HTTP, statistics)."""

    config: SkillConfig
    skill: str
    settings: RouterSettings
    state_dir: Path | None
    clock: Callable[[], float]
    node: RosNode | None
    url: str | None
    _active: dict[str, Where | None]
    _containers: dict[tuple[str, str], dict[str, Any]]
    _topics: dict[str, RoutedTopic]
    _services: dict[str, RoutedService]
    _http: list[HttpRoute]
    _http_counts: dict[str, list[int]]  # component -> [requests, bytes, errors]
    _inflight: dict[tuple[str, str], int]
    _drained: dict[tuple[str, str], asyncio.Event]
    _calls_lock: threading.Lock
    _statistics: Publication | None
    _last_traffic: dict[str, tuple[float, tuple[int, int, int, int]]]
    _runner: web.AppRunner | None
    _session: aiohttp.ClientSession | None
    _started: float
    _r2_services: dict[str, Any]  # router.ros2

    def _r2_publish_statistics(self, windows: list[Any]) -> None:
        """Publish the ROS 2 topics' closed statistics windows (router.ros2 does)."""

    def r2_statistics(self) -> dict[str, dict[str, Any]]:
        """Return the ROS 2 services' totals (router.ros2 does)."""
        return {}

    def _enter(self, key: tuple[str, str]) -> None:
        """Count a request or call on its way to one instance."""
        with self._calls_lock:
            self._inflight[key] = self._inflight.get(key, 0) + 1

    def _leave(self, key: tuple[str, str], loop: asyncio.AbstractEventLoop | None = None) -> None:
        """Count one finished; wake a switch waiting for the instance to drain (``loop``: from another thread)."""
        with self._calls_lock:
            left = self._inflight[key] = self._inflight[key] - 1
            drained = self._drained.pop(key, None) if not left else None
        if drained is not None:
            if loop is None:
                drained.set()
            else:
                loop.call_soon_threadsafe(drained.set)
