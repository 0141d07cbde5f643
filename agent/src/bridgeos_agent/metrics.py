"""The agent's Prometheus metrics, served by `bridgeos-agent run --metrics HOST:PORT`.

The agent is one process, so nothing here needs prometheus_client's shared value files:
its parts bump plain integers on `AgentMetrics` (a dict increment, no lock), and a collector
turns them, the outbox, the link and each Skill router's own counters into metric families
when Prometheus scrapes. The router's per-topic counts already exist for the Skill manager,
so routing a message costs nothing extra.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator
from typing import TYPE_CHECKING, Any

from aiohttp import web
from prometheus_client import CollectorRegistry, ProcessCollector, generate_latest
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.exposition import CONTENT_TYPE_PLAIN_0_0_4
from prometheus_client.registry import Collector

from bridgeos_agent import __version__

if TYPE_CHECKING:
    from bridgeos_agent.controller import RobotController
    from bridgeos_agent.outbox import Outbox

PREFIX = "bridgeos_agent"


def parse_address(text: str) -> tuple[str, int]:
    """Split HOST:PORT (IPv6 as [::1]:PORT) into host and port, raising ValueError with the reason."""
    host, sep, port_text = text.rpartition(":")
    if not sep or not host:
        raise ValueError(f"{text!r} is not HOST:PORT")
    host = host.removeprefix("[").removesuffix("]")
    try:
        port = int(port_text)
    except ValueError:
        raise ValueError(f"{text!r}: port {port_text!r} is not a number") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"{text!r}: port {port} is outside 0-65535")
    return host, port


class AgentMetrics:
    """What the agent's parts count between scrapes: links, decisions, migrations, restarts."""

    def __init__(self, robot: str) -> None:
        self.robot = robot
        self.connections = 0
        self.decisions: Counter[tuple[str, str]] = Counter()  # (skill, stay|migrate)
        self.migrations: Counter[tuple[str, str]] = Counter()  # (skill, done|failed|abandoned)
        self.component_restarts: Counter[tuple[str, str]] = Counter()  # (skill, component)
        self.image_bytes: Counter[tuple[str, str]] = Counter()  # (skill, component): compressed bytes pulled

    def connected(self) -> None:
        """Count an accepted connection to the cloud (every one after the first is a reconnect)."""
        self.connections += 1

    def decided(self, skill: str, decisions: Iterable[Any]) -> None:
        """Count one round of a Skill manager's offloading decisions."""
        for decision in decisions:
            self.decisions[(skill, "migrate" if decision.migrate else "stay")] += 1

    def migrated(self, skill: str, outcome: str) -> None:
        """Count a migration's outcome: done, failed or abandoned."""
        self.migrations[(skill, outcome)] += 1

    def component_restarted(self, skill: str, component: str) -> None:
        """Count a crashed component's restart by the runtime."""
        self.component_restarts[(skill, component)] += 1

    def image_pulled(self, skill: str, component: str, count: int) -> None:
        """Count bytes of a component's image pulled from the registry."""
        self.image_bytes[(skill, component)] += count


class AgentCollector(Collector):
    """Turn the agent's counters, outbox, link and Skill routers into metric families at scrape time."""

    def __init__(
        self,
        counts: AgentMetrics,
        outbox: Outbox,
        link: asyncio.Event,
        routers: Callable[[], Iterable[tuple[str, Any]]],
        points: Callable[[], tuple[int, int, int]] | None = None,
        log_lines: Callable[[], tuple[int, int]] | None = None,
    ) -> None:
        self.points = points  # (metric points sent, dropped, unstored frames in flight) by the session
        self.log_lines = log_lines  # (component log lines shipped, dropped) by the log shipper
        self.counts = counts
        self.outbox = outbox
        self.link = link
        self.routers = routers  # (skill, router) of every Skill that runs one, asked at each scrape

    def collect(self) -> Iterator[Metric]:
        counts = self.counts
        robot = counts.robot
        info = GaugeMetricFamily(f"{PREFIX}_info", "The agent's version.", labels=["robot", "version"])
        info.add_metric([robot, __version__], 1)
        yield info
        yield from self._outbox(robot)
        link = GaugeMetricFamily(f"{PREFIX}_link_up", "1 while connected to the cloud.", labels=["robot"])
        link.add_metric([robot], 1.0 if self.link.is_set() else 0.0)
        yield link
        reconnects = CounterMetricFamily(
            f"{PREFIX}_reconnects", "Connections to the cloud after the first.", labels=["robot"]
        )
        reconnects.add_metric([robot], max(0, counts.connections - 1))
        yield reconnects
        outcome = ["skill", "outcome"]
        yield _counter(f"{PREFIX}_decisions", "Offloading decisions by outcome.", outcome, robot, counts.decisions)
        yield _counter(f"{PREFIX}_migrations", "Component migrations by outcome.", outcome, robot, counts.migrations)
        yield _counter(
            f"{PREFIX}_component_restarts",
            "Restarts of crashed components on the robot.",
            ["skill", "component"],
            robot,
            counts.component_restarts,
        )
        yield _counter(
            f"{PREFIX}_image_pull_bytes",
            "Bytes (compressed) of components' images pulled from the registry.",
            ["skill", "component"],
            robot,
            counts.image_bytes,
        )
        yield from self._routers(robot)
        if self.log_lines is not None:
            shipped, dropped = self.log_lines()
            for name, doc, value in (
                ("log_lines_shipped", "Component log lines the cloud acknowledged.", shipped),
                (
                    "log_lines_dropped",
                    "Component log lines never shipped: over the cap, or overwritten in the ring.",
                    dropped,
                ),
            ):
                counter = CounterMetricFamily(f"{PREFIX}_{name}", doc, labels=["robot"])
                counter.add_metric([robot], value)
                yield counter

    def _outbox(self, robot: str) -> Iterator[Metric]:
        stats = self.outbox.stats()
        oldest = self.outbox.oldest_ts()
        for name, doc, value in (
            ("outbox_frames", "Frames kept until the cloud acknowledges them.", stats.frames),
            ("outbox_bytes", "Bytes of the frames the outbox keeps.", stats.bytes),
            (
                "outbox_oldest_age_seconds",
                "Age of the oldest unacknowledged frame (0 when empty).",
                max(0.0, time.time() - oldest) if oldest is not None else 0.0,
            ),
        ):
            family = GaugeMetricFamily(f"{PREFIX}_{name}", doc, labels=["robot"])
            family.add_metric([robot], value)
            yield family
        thinned = CounterMetricFamily(
            f"{PREFIX}_outbox_thinned_frames", "Metric frames dropped to keep the outbox in its size.", labels=["robot"]
        )
        thinned.add_metric([robot], stats.thinned_frames)
        yield thinned
        unstored = CounterMetricFamily(
            f"{PREFIX}_outbox_unstored_points",
            "Metric points the outbox could not keep: the disk was full and the memory budget spent.",
            labels=["robot"],
        )
        unstored.add_metric([robot], stats.unstored_points)
        yield unstored
        spilled = CounterMetricFamily(
            f"{PREFIX}_outbox_spilled_points",
            "Metric points kept in memory because the disk was full.",
            labels=["robot"],
        )
        spilled.add_metric([robot], stats.spilled_points)
        yield spilled
        for name, doc, value in (
            ("outbox_disk_full", "1 while the outbox's disk is full.", 1.0 if self.outbox.disk_full else 0.0),
            ("outbox_spilled_frames", "Frames kept in memory because the disk is full.", stats.spilled_frames),
            (
                "outbox_spilled_bytes",
                "Bytes of the frames kept in memory because the disk is full.",
                stats.spilled_bytes,
            ),
        ):
            family = GaugeMetricFamily(f"{PREFIX}_{name}", doc, labels=["robot"])
            family.add_metric([robot], value)
            yield family
        if self.points is not None:
            sent, dropped, in_flight = self.points()
            for name, doc, value in (
                ("metric_points_sent", "Metric points the agent produced for the cloud.", sent),
                (
                    "metric_points_dropped",
                    "Metric points neither kept (full disk, memory budget spent) nor sent (no link).",
                    dropped,
                ),
            ):
                counter = CounterMetricFamily(f"{PREFIX}_{name}", doc, labels=["robot"])
                counter.add_metric([robot], value)
                yield counter
            flying = GaugeMetricFamily(
                f"{PREFIX}_unstored_frames_in_flight",
                "Metric frames sent but not kept (full disk, memory budget spent), not acked yet.",
                labels=["robot"],
            )
            flying.add_metric([robot], in_flight)
            yield flying

    def _routers(self, robot: str) -> Iterator[Metric]:
        labels = ["robot", "skill", "topic"]
        messages = CounterMetricFamily(f"{PREFIX}_router_messages", "Messages routed per topic.", labels=labels)
        dropped = CounterMetricFamily(
            f"{PREFIX}_router_dropped", "Messages dropped on the way to a slow peer, per topic.", labels=labels
        )
        for skill_id, router in self.routers():
            # The router's own counters, kept for the Skill manager: routing pays nothing for them.
            for name, figures in router.statistics().items():
                if figures.get("kind") == "topic":
                    messages.add_metric([robot, skill_id, name], figures["messages"])
                    dropped.add_metric([robot, skill_id, name], figures["dropped"])
        yield messages
        yield dropped


def _counter(
    name: str, doc: str, labels: list[str], robot: str, counts: Counter[tuple[str, str]]
) -> CounterMetricFamily:
    family = CounterMetricFamily(name, doc, labels=["robot", *labels])
    for key, value in list(counts.items()):
        family.add_metric([robot, *key], value)
    return family


def controller_collector(controller: RobotController) -> AgentCollector:
    """Return the collector of one Robot Controller's metrics."""

    def routers() -> Iterator[tuple[str, Any]]:
        for skill_id, record in list(controller.skills.items()):
            router = record.context("router")
            if router is not None:
                yield skill_id, router

    def points() -> tuple[int, int, int]:
        session = controller.session
        return session.metric_points_sent, session.metric_points_dropped, session.unstored_in_flight

    def log_lines() -> tuple[int, int]:
        shipper = controller.logs.shipper
        return shipper.shipped_lines, shipper.dropped_lines

    return AgentCollector(controller.metrics, controller.outbox, controller.connected, routers, points, log_lines)


def registry_for(collector: Collector) -> CollectorRegistry:
    """Return a registry with the agent's collector and this process's CPU and memory."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    ProcessCollector(namespace=PREFIX, registry=registry)
    return registry


async def serve(controller: RobotController | AgentCollector, address: str) -> web.AppRunner:
    """Serve /metrics on HOST:PORT from the agent's event loop; the caller cleans the runner up."""
    host, port = parse_address(address)
    collector = controller if isinstance(controller, AgentCollector) else controller_collector(controller)
    registry = registry_for(collector)

    async def metrics(request: web.Request) -> web.Response:
        # Built on the loop's thread: the outbox's SQLite connection belongs to it.
        body = generate_latest(registry)
        return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_PLAIN_0_0_4})

    async def index(request: web.Request) -> web.Response:
        return web.Response(text=json.dumps({"metrics": "/metrics"}), content_type="application/json")

    app = web.Application()
    app.router.add_get("/metrics", metrics)
    app.router.add_get("/", index)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    await web.TCPSite(runner, host, port).start()
    return runner
