"""The Skill Router (thesis §3.4.2): hides where each component of a Skill runs.

Every component instance runs in a namespace of its own (``rosnames.instance_namespace``),
so the robot and cloud copies of a component never meet. The router relays each topic of
the Skill's ``router`` section from the publisher's *active* instance to the canonical name
and to every subscriber's active instance (and from outside publishers on the canonical
name to the subscribers), proxies ROS services and HTTP routes to the server's active
instance, and switches an instance active with one flag once the new one is ready. It
forwards message bytes without decoding them, keeps one bounded queue per subscriber
connection so a slow peer or a big topic never delays another, keeps the last N messages
of marked topics for new instances, counts everything for the Skill Manager and publishes
``rosgraph_msgs/TopicStatistics`` on ``/statistics``.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import ipaddress
import logging
import math
import os
import re
import time
from collections import deque
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import aiohttp
from aiohttp import web

from bridgeos_agent.rosnames import canonical_name, instance_name
from bridgeos_agent.rosnode import (
    Inbound,
    MasterError,
    Outbound,
    Publication,
    RosNode,
    Subscription,
    iter_frames,
    read_header,
)
from bridgeos_agent.skillconfig import HttpRoute, ServiceRoute, SkillConfig, TopicRoute
from bridgeos_agent.tcpros import (
    TOPIC_STATISTICS_DEFINITION,
    TOPIC_STATISTICS_MD5,
    TOPIC_STATISTICS_TYPE,
    HeaderError,
    TopicStatistics,
    encode_header,
    frame,
    header_stamp,
)
from bridgeos_agent.traffic import ComponentTraffic

if TYPE_CHECKING:
    from bridgeos_agent.supervisor import SkillSupervisor

__all__ = ["RouterSettings", "SkillRouter", "router_settings_from_env", "skill_router_plugin"]

logger = logging.getLogger(__name__)

Where = Literal["robot", "cloud"]
LOCATIONS: tuple[Where, ...] = ("robot", "cloud")
STATISTICS_TOPIC = "/statistics"
# Request headers that belong to one hop, not to the request (RFC 9110 §7.6.1).
HOP_HEADERS = frozenset(
    {
        "connection",
        "keep-alive",
        "proxy-authenticate",
        "proxy-authorization",
        "te",
        "trailer",
        "transfer-encoding",
        "upgrade",
        "host",
        "content-length",
    }
)


class RouterSettings:
    """Where the router listens and what it advertises (from the environment by default)."""

    def __init__(
        self,
        *,
        http_host: str = "0.0.0.0",
        http_advertise: str = "127.0.0.1",
        ros_host: str = "127.0.0.1",
        ready_timeout: float = 30.0,
        statistics_period: float = 1.0,
        drain_timeout: float = 10.0,
    ) -> None:
        for name, value in (("http_host", http_host), ("http_advertise", http_advertise), ("ros_host", ros_host)):
            if not value or any(c.isspace() for c in value) or "/" in value:
                raise ValueError(f"router setting {name}: {value!r} is not a host name or address")
        for name, value in (
            ("ready_timeout", ready_timeout),
            ("statistics_period", statistics_period),
            ("drain_timeout", drain_timeout),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"router setting {name}: must be a positive number of seconds, not {value!r}")
        self.http_host = http_host
        self.http_advertise = http_advertise
        self.ros_host = ros_host
        self.ready_timeout = ready_timeout
        self.statistics_period = statistics_period
        self.drain_timeout = drain_timeout


def router_settings_from_env(env: Mapping[str, str] | None = None) -> RouterSettings:
    """Read the router's settings: BRIDGEOS_ROUTER_HTTP_HOST/_ADVERTISE, ROS_IP or ROS_HOSTNAME, timeouts."""
    env = os.environ if env is None else env

    def seconds(name: str, default: float) -> float:
        raw = env.get(name)
        if raw is None or raw == "":
            return default
        try:
            return float(raw)
        except ValueError:
            raise ValueError(f"{name}: {raw!r} is not a number of seconds") from None

    http_host = env.get("BRIDGEOS_ROUTER_HTTP_HOST") or "0.0.0.0"
    default_advertise = "127.0.0.1" if http_host in ("0.0.0.0", "::") else http_host
    return RouterSettings(
        http_host=http_host,
        http_advertise=env.get("BRIDGEOS_ROUTER_HTTP_ADVERTISE") or default_advertise,
        ros_host=env.get("ROS_IP") or env.get("ROS_HOSTNAME") or "127.0.0.1",
        ready_timeout=seconds("BRIDGEOS_ROUTER_READY_TIMEOUT", 30.0),
        statistics_period=seconds("BRIDGEOS_ROUTER_STATISTICS_PERIOD", 1.0),
    )


def _locations(where: str) -> tuple[Where, ...]:
    return LOCATIONS if where == "either" else ((where,) if where in LOCATIONS else ())  # type: ignore[return-value]


class _Delivery:
    """What one subscriber component of a topic received, split by where its source ran."""

    # "robot" and "cloud": the router's publication in that instance's namespace (slots, not a dict:
    # a router may map tens of thousands of topics).
    __slots__ = ("bytes_cloud", "bytes_robot", "cloud", "dropped", "messages", "robot")

    def __init__(self) -> None:
        self.robot: Publication | None = None
        self.cloud: Publication | None = None
        self.messages = 0
        self.dropped = 0
        self.bytes_robot = 0
        self.bytes_cloud = 0


class _Topic:
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
        "messages",
        "node_pub",
        "outside_dropped",
        "outside_messages",
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
        self.deliveries: dict[str, _Delivery] = {}
        self.store: deque[bytes] | None = deque(maxlen=route.store) if route.store else None
        self.has_header = False
        self.node_pub = ""
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


class _Service:
    """One proxied service and its counters."""

    __slots__ = ("bytes", "calls", "canonical", "errors", "route")

    def __init__(self, route: ServiceRoute) -> None:
        self.route = route
        self.canonical = canonical_name(route.name)
        self.calls = 0
        self.bytes = 0
        self.errors = 0


class SkillRouter:
    """Route one Skill's ROS topics, ROS services and HTTP requests to its active instances."""

    def __init__(
        self,
        config: SkillConfig,
        *,
        ros_master: str | None,
        settings: RouterSettings | None = None,
        state_dir: Path | None = None,
        robot: str | None = None,
        clock: Any = time.monotonic,
    ) -> None:
        self.config = config
        self.skill = config.skill_id
        self.ros_master = ros_master
        self.settings = settings or RouterSettings()
        self.state_dir = state_dir
        self.clock = clock
        # Robots may share a master (the cloud's): a node name of the robot's own keeps two
        # routers of one Skill from evicting each other's registrations.
        suffix = "_" + re.sub(r"[^A-Za-z0-9_]", "_", robot) if robot else ""
        self.node_name = f"/bridgeos/{self.skill.replace('-', '_')}/router{suffix}"
        self.node: RosNode | None = None
        self.url: str | None = None  # the HTTP routes' base URL, when there are any
        self.ros_off_reason: str | None = None
        self._active: dict[str, Where | None] = {}
        self._containers: dict[tuple[str, str], dict[str, Any]] = {}
        self._topics: dict[str, _Topic] = {}
        self._services: dict[str, _Service] = {}
        self._http: list[HttpRoute] = []
        self._http_counts: dict[str, list[int]] = {}  # component -> [requests, bytes, errors]
        self._inflight: dict[tuple[str, str], int] = {}
        self._drained: dict[tuple[str, str], asyncio.Event] = {}
        self._statistics: Publication | None = None
        self._last_traffic: dict[str, tuple[float, tuple[int, int, int, int]]] = {}
        self._runner: web.AppRunner | None = None
        self._session: aiohttp.ClientSession | None = None
        self._tasks: set[asyncio.Task] = set()
        self._ros_warned = False
        self._started = clock()

    # ------------------------------------------------------------------ life cycle

    @property
    def ros_routes(self) -> bool:
        """Tell whether the Skill has any ROS topic or service to route."""
        return bool(self.config.router.topics or self.config.router.services)

    @property
    def ros_on(self) -> bool:
        """Tell whether ROS routing runs."""
        return self.node is not None

    async def start(self) -> None:
        """Start HTTP routing (if any routes) and ROS routing (if any routes and a master)."""
        if self.config.router.http:
            await self._start_http()
        if self.ros_routes:
            await self.enable_ros(self.ros_master)

    async def enable_ros(self, master: str | None) -> bool:
        """Start ROS routing against ``master``; say once, clearly, when it cannot run."""
        if self.node is not None or not self.ros_routes:
            return self.node is not None
        self.ros_master = master
        if not master:
            self._ros_off("no ROS master is configured or reachable")
            return False
        node = RosNode(
            self.node_name,
            master,
            host=self.settings.ros_host,
            on_publisher_header=self._on_publisher_header,
        )
        try:
            await node.start()
        except (MasterError, OSError) as exc:
            self._ros_off(str(exc))
            return False
        self.node = node
        self.ros_off_reason = None
        self._statistics = node.advertise(STATISTICS_TOPIC, TOPIC_STATISTICS_TYPE)
        self._statistics.md5sum = TOPIC_STATISTICS_MD5
        self._statistics.definition = TOPIC_STATISTICS_DEFINITION
        for route in self.config.router.topics:
            self._add_topic(route)
        for route in self.config.router.services:
            self._add_service(route)
        errors = await node.settle()
        if errors:
            logger.warning("skill %s: %d ROS registration(s) failed, e.g. %s", self.skill, len(errors), errors[0])
        self._spawn(self._statistics_loop())
        logger.info(
            "skill %s: routing %d topic(s) and %d service(s) through %s",
            self.skill,
            len(self._topics),
            len(self._services),
            master,
        )
        return True

    def _ros_off(self, reason: str) -> None:
        self.ros_off_reason = reason
        if not self._ros_warned:
            self._ros_warned = True
            logger.warning("skill %s: ROS routing is off (%s); HTTP routing still works", self.skill, reason)

    async def close(self) -> None:
        """Stop routing: unregister from the master, close servers and connections."""
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.node is not None:
            node, self.node = self.node, None
            await node.close()
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._session is not None:
            await self._session.close()
            self._session = None

    def _spawn(self, coroutine: Any) -> None:
        task = asyncio.get_running_loop().create_task(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # ------------------------------------------------------------------ locations

    def active(self, component: str) -> Where | None:
        """Return the location whose instance of ``component`` the router routes to, if any."""
        return self._active.get(component)

    def set_active(self, component: str, location: str | None) -> None:
        """Make an instance active at once (a component's first start, or its stop)."""
        self._check(component, location)
        self._active[component] = location  # type: ignore[assignment]

    async def switch(self, component: str, location: str) -> None:
        """Route to ``location``'s instance from now on; return once the old one's calls have ended."""
        self._check(component, location)
        if location is None:
            raise ValueError("switch needs a location")
        old = self._active.get(component)
        self._active[component] = location  # type: ignore[assignment]
        # Topics switch in one step of the event loop: a burst goes wholly to the old or the new
        # instance. Requests and service calls already on their way finish at the old instance.
        if old is not None and old != location:
            key = (component, old)
            if self._inflight.get(key):
                drained = self._drained.setdefault(key, asyncio.Event())
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(drained.wait(), self.settings.drain_timeout)
        logger.info("skill %s: %s now routed to its %s instance", self.skill, component, location)

    def _check(self, component: str, location: str | None) -> None:
        config = self.config.components.get(component)
        if config is None:
            raise ValueError(f"skill {self.skill!r} has no component {component!r}")
        if location is not None and location not in _locations(config.location):
            raise ValueError(f"component {component!r} cannot run on the {location!r}")

    def _enter(self, key: tuple[str, str]) -> None:
        self._inflight[key] = self._inflight.get(key, 0) + 1

    def _leave(self, key: tuple[str, str]) -> None:
        left = self._inflight[key] = self._inflight[key] - 1
        if not left:
            drained = self._drained.pop(key, None)
            if drained is not None:
                drained.set()

    def set_container(self, component: str, location: str, container: Mapping[str, Any]) -> None:
        """Learn where an instance listens (``address`` and ``ports`` {"container port": published port})."""
        self._check(component, location)
        self._containers[(component, location)] = dict(container)

    async def wait_ready(self, component: str, location: str, timeout: float) -> bool:
        """Wait until ``location``'s instance of a component is connected (ROS) and answering (HTTP)."""
        self._check(component, location)
        deadline = time.monotonic() + timeout
        while True:
            if await self._ready(component, location):  # type: ignore[arg-type]
                return True
            if time.monotonic() >= deadline:
                return False
            await asyncio.sleep(0.05)

    async def _ready(self, component: str, location: Where) -> bool:
        node = self.node
        if node is not None:
            for topic in self._topics.values():
                route = topic.route
                if route.publisher == component:
                    subscription = node.subscriptions.get(instance_name(route.name, self.skill, component, location))
                    if subscription is None or not subscription.connected:
                        return False
                delivery = topic.deliveries.get(component) if component != route.publisher else None
                if delivery is not None:
                    publication = getattr(delivery, location)
                    if publication is None or not publication.connections:
                        return False
            for service in self._services.values():
                if service.route.server == component:
                    name = instance_name(service.route.name, self.skill, component, location)
                    if await node.lookup_service(name) is None:
                        return False
        for route in self._http:
            if route.component == component and not await self._http_answers(route, location):
                return False
        return True

    # ------------------------------------------------------------------ topics

    def _add_topic(self, route: TopicRoute) -> None:
        node = self.node
        assert node is not None
        components = self.config.components
        canonical = canonical_name(route.name)
        topic = _Topic(route, node.advertise(canonical, route.type), self.clock())
        self._topics[canonical] = topic
        for subscriber in route.subscribers:
            if subscriber == route.publisher:
                continue  # never route a component's own messages back to it
            delivery = topic.deliveries[subscriber] = _Delivery()
            for location in _locations(components[subscriber].location):
                publication = node.advertise(instance_name(route.name, self.skill, subscriber, location), route.type)
                setattr(delivery, location, publication)
                if topic.store is not None:
                    publication.on_connect = functools.partial(self._replay, topic)
        for location in _locations(components[route.publisher].location):
            name = instance_name(route.name, self.skill, route.publisher, location)
            subscription = node.subscribe(name, route.type, self._on_messages)
            subscription.owner, subscription.where = topic, location
        if topic.deliveries:
            # Outside publishers on the canonical name reach the subscribers too.
            node.subscribe(canonical, route.type, self._on_messages).owner = topic

    def _publications(self, topic: _Topic) -> list[Publication]:
        found = [topic.canonical_pub] if topic.canonical_pub is not None else []
        for delivery in topic.deliveries.values():
            found += [p for p in (delivery.robot, delivery.cloud) if p is not None]
        return found

    def _remove_topic(self, canonical: str) -> None:
        node = self.node
        topic = self._topics.pop(canonical, None)
        if node is None or topic is None:
            return
        for publication in self._publications(topic):
            node.unadvertise(publication.name)
        for name, subscription in list(node.subscriptions.items()):
            if subscription.owner is topic:
                node.unsubscribe(name)

    def _on_publisher_header(self, subscription: Subscription, inbound: Inbound) -> None:
        topic: _Topic | None = subscription.owner
        header = inbound.header or {}
        md5sum = header.get("md5sum", "*")
        if topic is None or md5sum == "*":
            return
        definition = header.get("message_definition", "")
        type_ = header.get("type", topic.route.type)
        for publication in self._publications(topic):
            publication.md5sum, publication.type, publication.definition = md5sum, type_, definition
        first = next((line.split() for line in definition.splitlines() if line.strip() and line[0] != "#"), [])
        topic.has_header = first[:1] in (["Header"], ["std_msgs/Header"])
        if subscription.where is not None:
            topic.node_pub = header.get("callerid", "")

    def _on_messages(self, subscription: Subscription, blob: bytes, count: int, inbound: Inbound) -> None:
        """Relay a burst of frames from one publisher: the router's hot path."""
        topic: _Topic = subscription.owner
        source = subscription.where
        payload = len(blob) - 4 * count
        dropped = 0
        active = self._active
        if source is None:
            # An outside publisher on the canonical name: to every subscriber's active instance.
            topic.outside_messages += count
            for component, delivery in topic.deliveries.items():
                where = active.get(component)
                if where is None:
                    continue
                lost = getattr(delivery, where).send(blob, count)
                delivery.messages += count - lost
                delivery.dropped += lost
                delivery.bytes_robot += payload  # outside nodes live on the robot's ROS graph
                dropped += lost
            topic.outside_dropped += dropped
        else:
            if active.get(topic.route.publisher) != source:
                return  # the inactive instance's traffic goes nowhere
            topic.messages += count
            canonical = topic.canonical_pub
            if canonical is not None and canonical.connections:
                lost = canonical.send(blob, count)
                dropped += lost
                topic.canonical_delivered += count - lost
                topic.bytes_robot += payload
            for component, delivery in topic.deliveries.items():
                where = active.get(component)
                if where is None:
                    continue
                lost = getattr(delivery, where).send(blob, count)
                delivery.messages += count - lost
                delivery.dropped += lost
                dropped += lost
                if where == "robot":
                    topic.bytes_robot += payload
                else:
                    topic.bytes_cloud += payload
                if source == "robot":
                    delivery.bytes_robot += payload
                else:
                    delivery.bytes_cloud += payload
            topic.dropped += dropped
        if topic.store is not None:
            topic.store.extend(iter_frames(blob))
        # The statistics window.
        now = self.clock()
        topic.w_messages += count
        topic.w_bytes += payload
        topic.w_dropped += dropped
        if topic.w_last:
            period = (now - topic.w_last) / count
            topic.w_period_n += count
            topic.w_period_sum += period * count
            topic.w_period_sq += period * period * count
            if period > topic.w_period_max:
                topic.w_period_max = period
        topic.w_last = now
        if topic.has_header:
            stamp = header_stamp(blob, 0)
            if stamp:
                age = time.time() - stamp
                topic.w_age_n += 1
                topic.w_age_sum += age
                topic.w_age_sq += age * age
                if age > topic.w_age_max:
                    topic.w_age_max = age

    def _replay(self, topic: _Topic, connection: Outbound) -> None:
        """Give a newly connected instance the topic's stored messages first."""
        if topic.store:
            connection.send(b"".join(topic.store), len(topic.store))

    # ------------------------------------------------------------------ statistics

    async def _statistics_loop(self) -> None:
        period = self.settings.statistics_period
        while True:
            await asyncio.sleep(period)
            self.publish_statistics()

    def publish_statistics(self) -> int:
        """Close every topic's statistics window; publish the busy ones on /statistics; return how many."""
        now = self.clock()
        wall = time.time()
        publication = self._statistics
        listening = publication is not None and publication.connections
        frames = []
        for topic in self._topics.values():
            span = now - topic.w_start
            topic.last_rate = topic.w_messages / span if span > 0 else 0.0
            topic.last_age = topic.w_age_sum / topic.w_age_n if topic.w_age_n else None
            if listening and topic.w_messages:
                frames.append(frame(self._window(topic, now, wall).serialize()))
            topic._reset_window(now)
            topic.w_last = 0.0
        if frames and publication is not None:
            publication.send(b"".join(frames), len(frames))
        return len(frames)

    def _window(self, topic: _Topic, now: float, wall: float) -> TopicStatistics:
        count, total, squares = topic.w_period_n, topic.w_period_sum, topic.w_period_sq
        mean = total / count if count else 0.0
        ages = (topic.w_age_n, topic.w_age_sum, topic.w_age_sq, topic.w_age_max)
        age_mean = ages[1] / ages[0] if ages[0] else 0.0
        return TopicStatistics(
            topic=topic.canonical,
            node_pub=topic.node_pub or topic.route.publisher,
            node_sub=self.node.name if self.node else "",
            window_start=wall - (now - topic.w_start),
            window_stop=wall,
            delivered_msgs=topic.w_messages,
            dropped_msgs=topic.w_dropped,
            traffic=topic.w_bytes,
            period_mean=mean,
            period_stddev=math.sqrt(max(0.0, squares / count - mean * mean)) if count else 0.0,
            period_max=topic.w_period_max,
            stamp_age_mean=age_mean,
            stamp_age_stddev=math.sqrt(max(0.0, ages[2] / ages[0] - age_mean * age_mean)) if ages[0] else 0.0,
            stamp_age_max=ages[3],
        )

    def statistics(self) -> dict[str, dict[str, Any]]:
        """Return each topic's and service's totals since the router started."""
        result: dict[str, dict[str, Any]] = {}
        for topic in self._topics.values():
            delivered = topic.canonical_delivered + sum(d.messages for d in topic.deliveries.values())
            dropped = topic.dropped + topic.outside_dropped
            sent = topic.messages + topic.outside_messages
            result[topic.canonical] = {
                "kind": "topic",
                "publisher": topic.route.publisher,
                "messages": sent,
                "bytes": topic.bytes_robot + topic.bytes_cloud,
                "delivered": delivered,
                "dropped": dropped,
                "delivery_ratio": delivered / (delivered + dropped) if delivered + dropped else 1.0,
                "rate_hz": round(topic.last_rate, 3),
                "latency_ms": None if topic.last_age is None else round(topic.last_age * 1000, 3),
                "subscribers": {
                    name: {"messages": d.messages, "dropped": d.dropped, "bytes": d.bytes_robot + d.bytes_cloud}
                    for name, d in topic.deliveries.items()
                },
            }
        for service in self._services.values():
            result[service.canonical] = {
                "kind": "service",
                "server": service.route.server,
                "calls": service.calls,
                "bytes": service.bytes,
                "errors": service.errors,
            }
        return result

    def _totals(self, component: str) -> tuple[int, int, int, int]:
        """Return (bytes robot, bytes cloud, messages, dropped) routed to or from a component so far."""
        robot = cloud = messages = dropped = 0
        for topic in self._topics.values():
            if topic.route.publisher == component:
                robot += topic.bytes_robot
                cloud += topic.bytes_cloud
                messages += topic.messages
                dropped += topic.dropped
            delivery = topic.deliveries.get(component)
            if delivery is not None:
                robot += delivery.bytes_robot
                cloud += delivery.bytes_cloud
                messages += delivery.messages + delivery.dropped
                dropped += delivery.dropped
        for service in self._services.values():
            if service.route.server == component:
                robot += service.bytes
                messages += service.calls
                dropped += service.errors
        counts = self._http_counts.get(component)
        if counts is not None:
            messages += counts[0]
            robot += counts[1]
            dropped += counts[2]
        return robot, cloud, messages, dropped

    def routed(self, component: str) -> bool:
        """Tell whether any route of the Skill's config involves a component."""
        router = self.config.router
        return (
            any(t.publisher == component or component in t.subscribers for t in router.topics)
            or any(s.server == component for s in router.services)
            or any(h.component == component for h in router.http)
        )

    def traffic(self, component: str) -> ComponentTraffic:
        """Return what was routed to or from a component since the previous call (the manager's input).

        Raises KeyError for a component no route involves: the router measures nothing of it.
        """
        if not self.routed(component):
            raise KeyError(f"skill {self.skill!r} routes nothing of component {component!r}")
        now = self.clock()
        totals = self._totals(component)
        since, before = self._last_traffic.get(component, (self._started, (0, 0, 0, 0)))
        self._last_traffic[component] = (now, totals)
        robot, cloud, messages, dropped = (a - b for a, b in zip(totals, before, strict=True))
        return ComponentTraffic(
            seconds=max(0.0, now - since),
            bytes_robot=robot,
            bytes_cloud=cloud,
            messages=messages,
            dropped=dropped,
        )

    # ------------------------------------------------------------------ services

    def _add_service(self, route: ServiceRoute) -> None:
        assert self.node is not None
        service = _Service(route)
        self._services[service.canonical] = service
        self.node.advertise_service(service.canonical, functools.partial(self._serve, service))

    def _remove_service(self, canonical: str) -> None:
        self._services.pop(canonical, None)
        if self.node is not None:
            self.node.unadvertise_service(canonical)

    async def _upstream(
        self, service: _Service, location: Where, request: dict[str, str]
    ) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, dict[str, str]]:
        """Open a connection to one instance's service and exchange headers."""
        assert self.node is not None
        name = instance_name(service.route.name, self.skill, service.route.server, location)
        where = await self.node.lookup_service(name)
        if where is None:
            raise ConnectionError(f"{service.route.server} serves no {name} on the {location}")
        reader, writer = await asyncio.wait_for(asyncio.open_connection(*where), 10)
        fields = {
            "callerid": self.node.name,
            "service": name,
            "md5sum": request.get("md5sum", "*"),
            "persistent": "1",
        }
        writer.write(encode_header(fields))
        header = await asyncio.wait_for(read_header(reader), 10)
        if "error" in header:
            writer.close()
            raise ConnectionError(header["error"])
        return reader, writer, header

    async def _serve(
        self, service: _Service, request: dict[str, str], reader: asyncio.StreamReader, writer: asyncio.StreamWriter
    ) -> None:
        """Proxy one client's calls, each to the server instance active when it arrives."""
        server = service.route.server
        location = self._active.get(server)
        if location is None:
            writer.write(encode_header({"error": f"{service.canonical}: component {server} is not running"}))
            return
        try:
            upstream = await self._upstream(service, location, request)
        except (ConnectionError, OSError, TimeoutError, HeaderError, asyncio.IncompleteReadError) as exc:
            writer.write(encode_header({"error": f"{service.canonical}: {exc}"}))
            return
        up_reader, up_writer, header = upstream
        writer.write(encode_header({**header, "callerid": self.node.name if self.node else ""}))
        try:
            while True:
                try:
                    size = int.from_bytes(await reader.readexactly(4), "little")
                    body = await reader.readexactly(size)
                except (asyncio.IncompleteReadError, ConnectionError):
                    return  # the client is done
                now_at = self._active.get(server)
                key = (server, now_at or location)
                self._enter(key)
                try:
                    if now_at != location or up_writer.is_closing():
                        up_writer.close()
                        if now_at is None:
                            raise ConnectionError(f"component {server} is not running")
                        location = now_at
                        up_reader, up_writer, _ = await self._upstream(service, location, request)
                    up_writer.write(size.to_bytes(4, "little") + body)
                    ok = await up_reader.readexactly(1)
                    length = int.from_bytes(await up_reader.readexactly(4), "little")
                    answer = await up_reader.readexactly(length)
                except (ConnectionError, OSError, TimeoutError, HeaderError, asyncio.IncompleteReadError) as exc:
                    service.errors += 1
                    message = f"{service.canonical}: {exc or type(exc).__name__}".encode()
                    writer.write(b"\x00" + len(message).to_bytes(4, "little") + message)
                    await writer.drain()
                    return
                finally:
                    self._leave(key)
                service.calls += 1
                service.bytes += size + length
                writer.write(ok + length.to_bytes(4, "little") + answer)
                await writer.drain()
        finally:
            up_writer.close()

    # ------------------------------------------------------------------ HTTP

    async def _start_http(self) -> None:
        self._http = sorted(self.config.router.http, key=lambda r: len(r.prefix), reverse=True)
        if self._runner is not None:
            return
        self._session = aiohttp.ClientSession(
            timeout=aiohttp.ClientTimeout(total=None, sock_connect=10), auto_decompress=False
        )
        app = web.Application(client_max_size=0)
        app.router.add_route("*", "/{tail:.*}", self._proxy)
        runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=5.0)
        await runner.setup()
        saved = self._saved_port()
        for port in dict.fromkeys((saved, 0)):
            try:
                await web.TCPSite(runner, self.settings.http_host, port).start()
                break
            except OSError:
                if port == 0:
                    await runner.cleanup()
                    raise
        self._runner = runner
        port = runner.addresses[0][1]
        host = self.settings.http_advertise
        self.url = f"http://{f'[{host}]' if ':' in host else host}:{port}"
        if self.state_dir is not None:
            self.state_dir.mkdir(parents=True, exist_ok=True)
            (self.state_dir / f"{self.skill}.port").write_text(str(port))

    def _saved_port(self) -> int:
        if self.state_dir is None:
            return 0
        try:
            port = int((self.state_dir / f"{self.skill}.port").read_text())
        except (OSError, ValueError):
            return 0
        return port if 1 <= port <= 65535 else 0

    def _match(self, path: str) -> HttpRoute | None:
        for route in self._http:
            prefix = route.prefix.rstrip("/")
            if not prefix or path == prefix or path.startswith(prefix + "/"):
                return route
        return None

    def _http_target(self, route: HttpRoute, location: str) -> tuple[str, int] | None:
        component = self.config.components[route.component]
        launch = component.launch_spec(location)  # type: ignore[arg-type]
        port = route.port or (launch.ports[0] if launch is not None and launch.ports else None)
        container = self._containers.get((route.component, location))
        if container is None or not (container.get("address") or container.get("ip") or container.get("host")):
            # A robot instance listens on the robot itself unless its runtime reported an address.
            return ("127.0.0.1", port) if location == "robot" and port else None
        host = container.get("address") or container.get("ip") or container.get("host")
        ports = container.get("ports")
        if isinstance(ports, Mapping):
            published = ports.get(str(port)) if port else next(iter(ports.values()), None)
        else:
            published = port
        if not host or not published:
            return None
        try:
            return str(host), int(published)
        except (TypeError, ValueError):
            return None

    async def _http_answers(self, route: HttpRoute, location: str) -> bool:
        target = self._http_target(route, location)
        if target is None or self._session is None:
            return False
        host, port = target
        url = f"http://{_url_host(host)}:{port}{route.prefix}"
        try:
            async with self._session.get(url, timeout=aiohttp.ClientTimeout(total=2)) as response:
                return response.status < 500
        except (aiohttp.ClientError, OSError, TimeoutError):
            return False

    async def _proxy(self, request: web.Request) -> web.StreamResponse:
        route = self._match(request.path)
        if route is None:
            return web.json_response({"error": f"no route for {request.path}"}, status=404)
        if request.method not in route.methods:
            return web.json_response(
                {"error": f"{request.method} is not routed on {route.prefix}"},
                status=405,
                headers={"Allow": ", ".join(route.methods)},
            )
        component = route.component
        location = self._active.get(component)
        target = self._http_target(route, location) if location else None
        counts = self._http_counts.setdefault(component, [0, 0, 0])
        if target is None or self._session is None:
            counts[2] += 1
            reason = "is not running" if location is None else f"has no known address on the {location}"
            return web.json_response({"error": f"component {component} {reason}"}, status=503)
        key = (component, location)
        self._enter(key)
        try:
            return await self._forward(request, target, counts)
        finally:
            self._leave(key)

    async def _forward(self, request: web.Request, target: tuple[str, int], counts: list[int]) -> web.StreamResponse:
        assert self._session is not None
        host, port = target
        url = f"http://{_url_host(host)}:{port}{request.rel_url}"
        headers = {k: v for k, v in request.headers.items() if k.lower() not in HOP_HEADERS}
        headers["X-Forwarded-For"] = request.remote or ""
        data = request.content if request.body_exists else None
        try:
            async with self._session.request(
                request.method, url, headers=headers, data=data, allow_redirects=False
            ) as upstream:
                response = web.StreamResponse(status=upstream.status, reason=upstream.reason)
                for key, value in upstream.headers.items():
                    if key.lower() not in HOP_HEADERS:
                        response.headers.add(key, value)
                if upstream.content_length is not None:
                    response.content_length = upstream.content_length
                await response.prepare(request)
                sent = 0
                async for chunk in upstream.content.iter_any():
                    sent += len(chunk)
                    await response.write(chunk)
                await response.write_eof()
        except (aiohttp.ClientError, OSError, TimeoutError) as exc:
            counts[2] += 1
            return web.json_response({"error": f"the component did not answer: {exc}"}, status=502)
        counts[0] += 1
        counts[1] += sent + (request.content_length or 0)
        return response

    # ------------------------------------------------------------------ runtime changes

    async def apply(self, config: SkillConfig) -> None:
        """Take a new Skill config: add, change and remove routes while the router runs."""
        old = self.config.router
        self.config = config
        if config.router.http:
            await self._start_http()
        else:
            self._http = []
        if self.node is None:
            if self.ros_routes:
                await self.enable_ros(self.ros_master)
            return
        before = {canonical_name(t.name): t for t in old.topics}
        after = {canonical_name(t.name): t for t in config.router.topics}
        for name, route in before.items():
            if after.get(name) != route:
                self._remove_topic(name)
        for name, route in after.items():
            if before.get(name) != route:
                self._add_topic(route)
        before_s = {canonical_name(s.name): s for s in old.services}
        after_s = {canonical_name(s.name): s for s in config.router.services}
        for name, route in before_s.items():
            if after_s.get(name) != route:
                self._remove_service(name)
        for name, route in after_s.items():
            if before_s.get(name) != route:
                self._add_service(route)
        errors = await self.node.settle()
        if errors:
            logger.warning("skill %s: %d ROS registration(s) failed, e.g. %s", self.skill, len(errors), errors[0])


def _url_host(host: str) -> str:
    with contextlib.suppress(ValueError):
        if ipaddress.ip_address(host).version == 6:
            return f"[{host}]"
    return host


async def skill_router_plugin(supervisor: SkillSupervisor) -> None:
    """Run a Skill's router as a supervisor plug-in (the controller is in the supervisor's context)."""
    controller: Any = supervisor.context["controller"]
    record = controller.skills[supervisor.skill]
    router = SkillRouter(
        record.config,
        ros_master=controller.ros_master,
        settings=router_settings_from_env(),
        state_dir=controller.data_dir / "router",
        robot=controller.settings.robot,
    )
    for name, location in record.locations.items():
        if location in LOCATIONS and name in record.config.components:
            router.set_active(name, location)
    supervisor.context["router"] = router
    try:
        await router.start()
        if router.url:
            supervisor.context.setdefault("env", {})["BRIDGEOS_ROUTER_URL"] = router.url
        supervisor.mark_ready("router")
        config = record.config
        ticks = 0
        while True:
            await asyncio.sleep(1.0)
            if record.config is not config:
                config = record.config
                await router.apply(config)
                if router.url:
                    supervisor.context.setdefault("env", {})["BRIDGEOS_ROUTER_URL"] = router.url
            ticks += 1
            if router.node is None and router.ros_routes and controller.ros_master and ticks % 5 == 0:
                await router.enable_ros(controller.ros_master)
    finally:
        await router.close()
