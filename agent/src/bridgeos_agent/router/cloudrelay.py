"""Cloud-side routing: a cloud relay delivers what goes from a cloud instance to a cloud instance.

The cloud relay is the same Skill Router code run in the cloud for one robot's Skill
(``python -m bridgeos_agent.router.cloudrelay``, started by the cloud's worker next to the
robot's ROS master). It advertises and subscribes only the *cloud* instances' names and
delivers only the (topic, subscriber) pairs whose publisher and subscriber are both active in
the cloud; the robot's router (through its :class:`CloudLink`) hands those pairs to it,
stops relaying them and stops subscribing to a cloud publisher nobody on the robot needs, so
their bytes no longer cross the robot's link (twice).

One relay is responsible for each pair at any moment. A handover is exact: the relay giving a
pair stops in one step of its event loop and names the last message it delivered by the
fingerprints of the last few frames it saw (``FrameLog``); the relay taking it delivers from the
next one, out of its own log of the same stream (or as soon as the cut point arrives). A pair
whose publisher changes in the handover starts afresh with the new publisher, as a switch inside
one router does, once the old relay's queue to that subscriber has drained. The robot's router
stays the authority on which instance is active: it sends its whole map with every handover.

The robot's router keeps the canonical names (outside nodes live on the robot's graph), the
services and the HTTP routes. Statistics: the relay publishes its own windows on
``/statistics`` and the robot's router adds the relay's totals (polled) to what it reports
to the Skill Manager. When no relay answers, the robot's router relays everything itself, as
before, and says so once in its log.

Limit: the cut point is found by content (length and CRC-32 of each frame's first and last
4 KiB, four frames in a row); a stream repeating four identical messages across a handover may
lose or repeat some of those identical messages.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import hmac
import json
import logging
import os
import secrets
import sys
import time
import zlib
from collections import deque
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import aiohttp
from aiohttp import web

from bridgeos_agent.rosnames import canonical_name, instance_name
from bridgeos_agent.rostopics import Publication, Subscription, iter_frames
from bridgeos_agent.router.core import SkillRouter
from bridgeos_agent.router.routes import Delivery, RoutedTopic
from bridgeos_agent.router.settings import RouterSettings, Where, locations
from bridgeos_agent.skillconfig import SkillConfig, parse_skill_config

if TYPE_CHECKING:
    from bridgeos_agent.router.routes import RouterBase

__all__ = ["CloudLink", "CloudRelay", "FrameLog", "cloud_pairs", "fingerprint", "link_from_env"]

logger = logging.getLogger(__name__)

ANCHOR = 4  # frames naming a cut point
LOG_FRAMES = 8192
LOG_BYTES = 64 << 20
QUIET_S = 0.05  # after a drain, before another relay writes to the same subscriber (its reader threads)
KEEP_S = 5.0  # a cloud source subscribed for a readiness check is kept this long
REFRESH_S = 2.0  # how often the relay asks the master about sources it has not heard yet
FAILURES = 3  # polls in a row without an answer before the robot takes every pair back

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


# --------------------------------------------------------------------------- the cloud side


class CloudRelay(SkillRouter):
    """A Skill Router run in the cloud for one robot: it delivers the pairs the robot's router hands it."""

    canonical_names = False

    def __init__(
        self,
        config: SkillConfig,
        *,
        ros_master: str,
        token: str,
        settings: RouterSettings | None = None,
        robot: str | None = None,
    ) -> None:
        super().__init__(config, ros_master=ros_master, settings=settings, robot=robot)
        self.node_name = self.node_name.replace("/router", "/cloudrelay", 1)
        self.token = token
        self.control_url: str | None = None
        self.control_port = 0  # the control API's port (0: any free one)
        self._control: web.AppRunner | None = None

    def _places(self, where: str) -> tuple[Where, ...]:
        return tuple(location for location in locations(where) if location == "cloud")

    def _add_topic(self, route: Any) -> None:
        super()._add_topic(route)
        topic = self._topics[canonical_name(route.name)]
        topic.log = FrameLog()
        for delivery in topic.deliveries.values():
            delivery.gate = AWAY  # nothing is ours until the robot's router hands it over
        topic.parked = True

    def _add_service(self, service: Any) -> None:
        """Leave services to the robot's router (it proxies each call to the active server)."""

    async def start(self) -> None:
        """Route the cloud instances' topics and serve the control API."""
        if self.ros_routes:
            await self.enable_ros(self.ros_master)
        app = web.Application(middlewares=[self._auth])
        app.router.add_post("/take", self._take)
        app.router.add_post("/release", self._release)
        app.router.add_post("/reset", self._reset)
        app.router.add_get("/ready", self._ready_view)
        app.router.add_get("/statistics", self._statistics_view)
        self._spawn(self._refresh_loop())
        self._control = web.AppRunner(app, access_log=None)
        await self._control.setup()
        site = web.TCPSite(self._control, self.settings.http_host, self.control_port)
        await site.start()
        port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
        self.control_url = f"http://{self.settings.http_advertise}:{port}"

    async def _refresh_loop(self) -> None:
        """Ask the master again for the publishers of every source not connected yet."""
        # The relay sits across the robot's link from the master (the robot's own, usually): a
        # lost publisherUpdate would otherwise leave a cloud source unheard for good.
        while True:
            await asyncio.sleep(REFRESH_S)
            node = self.node
            if node is None:
                continue
            for name, subscription in list(node.subscriptions.items()):
                if subscription.where is not None and not subscription.connected:
                    node.subscribe(name, subscription.type, subscription.callback)

    async def close(self) -> None:
        await super().close()
        if self._control is not None:
            await self._control.cleanup()
            self._control = None

    @web.middleware
    async def _auth(self, request: web.Request, handler: Any) -> web.StreamResponse:
        given = request.headers.get("Authorization", "")
        if not hmac.compare_digest(given.encode(), f"Bearer {self.token}".encode()):
            return web.json_response({"error": "a cloud relay answers only its robot's router"}, status=401)
        return await handler(request)

    async def _body(self, request: web.Request) -> tuple[dict[str, Where | None], list[list[Any]]]:
        """Read and check a handover request: the robot's active map and the pairs; raise 400 on anything wrong."""
        try:
            body = await request.json()
            active = body["active"]
            pairs = body["pairs"]
            if not isinstance(active, dict) or not isinstance(pairs, list):
                raise TypeError("active must be an object and pairs a list")
            for component, location in active.items():
                self._check(component, location)
            for pair in pairs:
                topic = self._topics.get(pair[0])
                if topic is None or pair[1] not in topic.deliveries:
                    raise ValueError(f"no routed pair {pair[0]!r} -> {pair[1]!r}")
        except (ValueError, TypeError, KeyError, IndexError) as exc:
            raise web.HTTPBadRequest(text=json.dumps({"error": str(exc)}), content_type="application/json") from None
        return active, pairs

    def _park(self) -> None:
        """Stop any pair the active map no longer makes cloud to cloud; mark topics with nothing to deliver."""
        pairs = cloud_pairs(self._topics.values(), self._active)
        for topic in self._topics.values():
            for subscriber, delivery in topic.deliveries.items():
                if delivery.gate is not AWAY and (topic.canonical, subscriber) not in pairs:
                    logger.warning("%s -> %s: no longer cloud to cloud; stopped", topic.canonical, subscriber)
                    delivery.gate = AWAY
        for topic in self._topics.values():
            topic.parked = all(d.gate is AWAY for d in topic.deliveries.values())

    async def _take(self, request: web.Request) -> web.Response:
        active, pairs = await self._body(request)
        for pair in pairs:
            if active.get(pair[1]) != "cloud" or active.get(self._topics[pair[0]].route.publisher) != "cloud":
                return web.json_response({"error": f"{pair[0]} -> {pair[1]} is not cloud to cloud"}, status=400)
        self._active = dict(active)
        for name, subscriber, anchor in pairs:
            topic = self._topics[name]
            start_after(topic, topic.deliveries[subscriber], "cloud", anchor, self.settings.drain_timeout)
        self._park()
        return web.json_response({"taken": len(pairs)})

    async def _release(self, request: web.Request) -> web.Response:
        active, pairs = await self._body(request)
        anchors, publications = [], []
        for name, subscriber in pairs:
            topic = self._topics[name]
            delivery = topic.deliveries[subscriber]
            was_ours = delivery.gate is None
            delivery.gate = AWAY
            publications.append(delivery.cloud)
            same_stream = was_ours and active.get(topic.route.publisher) == "cloud" and topic.log is not None
            anchors.append([name, subscriber, topic.log.anchor() if same_stream else None])
        self._active = dict(active)
        self._park()
        await drained(publications, self.settings.drain_timeout)
        await asyncio.sleep(QUIET_S)
        return web.json_response({"anchors": anchors})

    async def _reset(self, request: web.Request) -> web.Response:
        for topic in self._topics.values():
            for delivery in topic.deliveries.values():
                delivery.gate = AWAY
        self._park()
        return web.json_response({"reset": True})

    async def _ready_view(self, request: web.Request) -> web.Response:
        component = request.query.get("component", "")
        try:
            self._check(component, "cloud")
        except ValueError as exc:
            return web.json_response({"error": str(exc)}, status=400)
        return web.json_response({"ready": await self._ready(component, "cloud")})

    async def _statistics_view(self, request: web.Request) -> web.Response:
        counts = {
            name: {
                "messages": topic.messages,
                "bytes_cloud": topic.bytes_cloud,
                "dropped": topic.dropped,
                "deliveries": {
                    sub: [d.messages, d.dropped, d.bytes_robot, d.bytes_cloud] for sub, d in topic.deliveries.items()
                },
            }
            for name, topic in self._topics.items()
        }
        return web.json_response({"counts": counts})


# --------------------------------------------------------------------------- the robot side


class CloudLink:
    """The robot router's side: hand cloud-to-cloud pairs to the cloud relay and take them back."""

    def __init__(self, url: str, token: str, *, poll: float = 1.0) -> None:
        self.url = url.rstrip("/")
        self.token = token
        self.poll = poll
        self.up = False
        self.owned: set[Pair] = set()  # the pairs the cloud relay delivers
        self.seen: dict[str, Where | None] = {}  # the active map of the last handover
        self.counts: dict[str, dict[str, Any]] = {}  # the relay's totals, polled
        self.keep: dict[str, float] = {}  # cloud sources kept subscribed for a readiness check, until
        self.lock = asyncio.Lock()
        self.session: aiohttp.ClientSession | None = None
        self.reason: str | None = None
        self._task: asyncio.Task[None] | None = None
        self._failures = 0

    # -- plumbing

    async def _call(self, method: str, path: str, body: Any = None, **query: str) -> Any:
        assert self.session is not None
        async with self.session.request(
            method, self.url + path, json=body, params=query or None, headers={"Authorization": f"Bearer {self.token}"}
        ) as response:
            data = await response.json(content_type=None)
            if response.status != 200:
                raise ValueError(f"{path}: {response.status} {data.get('error') if isinstance(data, dict) else data}")
            return data

    async def start(self, router: SkillRouter) -> None:
        """Reach the relay and hand it the cloud-to-cloud pairs; say clearly when it cannot be reached."""
        self.session = aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=10))
        await self._connect(router)
        self._task = asyncio.get_running_loop().create_task(self._poll_loop(router))

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        if self.session is not None:
            await self.session.close()

    async def _connect(self, router: SkillRouter) -> bool:
        try:
            await self._call("POST", "/reset")
        except (aiohttp.ClientError, OSError, TimeoutError, ValueError) as exc:
            self._fall_back(router, f"cloud relay {self.url} unreachable ({exc or type(exc).__name__})")
            return False
        self.up, self.reason, self._failures = True, None, 0
        self.owned, self.seen = set(), {}
        for topic in router._topics.values():
            if topic.log is None:
                topic.log = FrameLog()
        logger.info("skill %s: cloud relay %s linked: cloud-to-cloud links stay in the cloud", router.skill, self.url)
        await self.handover(router, self.plan(router))
        return True

    def _fall_back(self, router: SkillRouter, reason: str) -> None:
        """Relay every pair on the robot again (today's routing)."""
        if self.reason is None:
            logger.warning(
                "skill %s: %s; the robot's router relays every link itself"
                " (cloud-to-cloud traffic crosses the robot's link)",
                router.skill,
                reason,
            )
        self.up, self.reason = False, reason
        for topic in router._topics.values():
            for delivery in topic.deliveries.values():
                delivery.gate = None  # handed over, held or awaiting a cut point: all ours again
        self.owned = set()
        self.seen = dict(router._active)
        self.prune(router)

    async def _poll_loop(self, router: SkillRouter) -> None:
        while True:
            await asyncio.sleep(self.poll)
            try:
                await self._poll_once(router)
            except Exception:  # the loop outlives a bug in one round; it is said in the log
                logger.exception("skill %s: polling the cloud relay failed", router.skill)

    async def _poll_once(self, router: SkillRouter) -> None:
        """Reconnect a fallen link, or fetch the relay's counts and catch up with the active map."""
        if not self.up:
            await self._connect(router)
            return
        try:
            self.counts = (await self._call("GET", "/statistics"))["counts"]
            self._failures = 0
        except (aiohttp.ClientError, OSError, TimeoutError, ValueError) as exc:
            self._failures += 1
            if self._failures >= FAILURES:
                self._fall_back(router, f"cloud relay {self.url} stopped answering ({exc or type(exc).__name__})")
            return
        if router._active != self.seen:
            await self.handover(router, self.plan(router))
        self.prune(router)

    # -- handovers

    def plan(self, router: SkillRouter) -> dict[str, Any]:
        """Change which relay delivers each pair, in this step of the event loop; return what to tell the relay."""
        for topic in router._topics.values():
            if topic.log is None:
                topic.log = FrameLog()
        want = cloud_pairs(router._topics.values(), router._active) if self.up else set()
        give, take = [], []
        for pair in sorted(want - self.owned):
            topic = router._topics[pair[0]]
            delivery = topic.deliveries[pair[1]]
            # The same cloud stream went through the robot until now: the relay goes on after our cut.
            same_stream = delivery.gate is None and self.seen.get(topic.route.publisher) == "cloud"
            anchor = topic.log.anchor() if same_stream and self._receiving(router, topic) else None
            delivery.gate = AWAY
            give.append([pair[0], pair[1], anchor, [delivery.robot, delivery.cloud]])
            self.owned.add(pair)
        for pair in sorted(self.owned - want):
            self.owned.discard(pair)
            held = router._topics.get(pair[0])
            if held is None or pair[1] not in held.deliveries:
                continue
            held.deliveries[pair[1]].gate = HOLD
            take.append(list(pair))
        self.seen = dict(router._active)
        return {"active": dict(router._active), "give": give, "take": take}

    async def handover(self, router: SkillRouter, plan: dict[str, Any]) -> None:
        """Tell the relay what it now delivers and take back what it no longer does."""
        async with self.lock:
            if not self.up:
                return
            try:
                # Taken back first: the relay must stop a pair before it learns the new map.
                if plan["take"]:
                    for name, _ in plan["take"]:
                        source = router._topics[name]
                        if router._active.get(source.route.publisher) == "cloud":
                            await self._subscribed(router, source, router.settings.ready_timeout)
                    answer = await self._call("POST", "/release", {"active": plan["active"], "pairs": plan["take"]})
                    for name, subscriber, anchor in answer["anchors"]:
                        topic = router._topics.get(name)
                        if topic is None or subscriber not in topic.deliveries:
                            continue
                        delivery = topic.deliveries[subscriber]
                        where = router._active.get(subscriber)
                        if delivery.gate is not HOLD:
                            continue
                        if where is None:
                            delivery.gate = None  # stopped: whichever instance starts next gets the stream
                        else:
                            start_after(topic, delivery, where, anchor, router.settings.drain_timeout)
                if plan["give"]:
                    await drained([p for g in plan["give"] for p in g[3]], router.settings.drain_timeout)
                    await asyncio.sleep(QUIET_S)
                await self._call("POST", "/take", {"active": plan["active"], "pairs": [g[:3] for g in plan["give"]]})
            except (aiohttp.ClientError, OSError, TimeoutError, ValueError) as exc:
                self._fall_back(router, f"cloud relay {self.url} failed a handover ({exc or type(exc).__name__})")
                return
            self.keep.clear()  # the readiness checks before this switch are over
            self.prune(router)

    # -- which cloud sources the robot receives

    def _source(self, router: SkillRouter, topic: RoutedTopic) -> str | None:
        route = topic.route
        if "cloud" not in router._places(router.config.components[route.publisher].location):
            return None
        return instance_name(route.name, router.skill, route.publisher, "cloud")

    def _receiving(self, router: SkillRouter, topic: RoutedTopic) -> bool:
        name = self._source(router, topic)
        node = router.node
        return bool(name and node is not None and name in node.subscriptions and node.subscriptions[name].connected)

    def _subscribe(self, router: SkillRouter, topic: RoutedTopic) -> Subscription | None:
        name = self._source(router, topic)
        node = router.node
        if name is None or node is None:
            return None
        subscription = node.subscriptions.get(name)
        if subscription is None:
            subscription = node.subscribe(name, topic.route.type, router._on_messages)
            subscription.owner, subscription.where = topic, "cloud"
        return subscription

    async def _subscribed(self, router: SkillRouter, topic: RoutedTopic, timeout: float) -> None:
        subscription = self._subscribe(router, topic)
        name = self._source(router, topic)
        if name:
            self.keep[name] = time.monotonic() + KEEP_S
        deadline = time.monotonic() + timeout
        while subscription is not None and not subscription.connected:  # a connection has no event to await
            if time.monotonic() >= deadline:
                return
            await asyncio.sleep(0.02)

    def prune(self, router: SkillRouter) -> None:
        """Receive a cloud publisher's stream only while something on the robot's side needs it."""
        node = router.node
        if node is None:
            return
        now = time.monotonic()
        active = router._active
        for topic in list(router._topics.values()):
            name = self._source(router, topic)
            if name is None:
                continue
            needed = not self.up or self.keep.get(name, 0) > now
            if not needed and active.get(topic.route.publisher) == "cloud":
                canonical = topic.canonical_pub
                needed = bool(canonical is not None and canonical.connections) or any(
                    d.gate is not AWAY and active.get(sub) is not None for sub, d in topic.deliveries.items()
                )
            if needed:
                self._subscribe(router, topic)
            elif name in node.subscriptions:
                node.unsubscribe(name)
                if topic.log is not None:
                    topic.log.clear()  # a gap: an anchor from before it would name the wrong frame

    async def ready(self, router: SkillRouter, component: str, location: Where) -> bool:
        """Tell whether both relays are ready for ``location``'s instance of a component to become active."""
        if not self.up:
            return True
        ok = True
        for topic in router._topics.values():
            route = topic.route
            if route.publisher != component and component not in topic.deliveries:
                continue
            # The robot receives a cloud publisher's stream when it delivers some of it: to this
            # subscriber's robot instance, or (the core's check for a publisher) to anyone.
            if route.publisher == component:
                needs_source = location == "cloud"
            else:
                needs_source = location == "robot" and router._active.get(route.publisher) == "cloud"
            if needs_source:
                name = self._source(router, topic)
                if name:
                    self.keep[name] = time.monotonic() + KEEP_S
                subscription = self._subscribe(router, topic)
                if subscription is not None and not subscription.connected:
                    ok = False
        if location == "cloud":
            try:
                ok = (await self._call("GET", "/ready", component=component))["ready"] and ok
            except (aiohttp.ClientError, OSError, TimeoutError, ValueError) as exc:
                self._fall_back(router, f"cloud relay {self.url} did not answer a readiness check ({exc})")
        return ok

    # -- statistics

    def merge(self, result: dict[str, dict[str, Any]]) -> None:
        """Add the relay's deliveries to the robot router's per-topic statistics."""
        for name, counts in self.counts.items():
            stats = result.get(name)
            if stats is None or stats.get("kind") != "topic":
                continue
            delivered = dropped = 0
            for subscriber, (messages, lost, bytes_robot, bytes_cloud) in counts["deliveries"].items():
                row = stats["subscribers"].setdefault(subscriber, {"messages": 0, "dropped": 0, "bytes": 0})
                row["messages"] += messages
                row["dropped"] += lost
                row["bytes"] += bytes_robot + bytes_cloud
                delivered += messages
                dropped += lost
            # Both relays may receive one message (each for its own pairs): count it once.
            stats["messages"] = max(stats["messages"], counts["messages"])
            stats["bytes"] += counts["bytes_cloud"]
            stats["delivered"] += delivered
            stats["dropped"] += dropped
            total = stats["delivered"] + stats["dropped"]
            stats["delivery_ratio"] = stats["delivered"] / total if total else 1.0

    def totals(self, router: RouterBase, component: str) -> tuple[int, int, int, int]:
        """Return the relay's (bytes robot, bytes cloud, messages, dropped) for a component, beyond the robot's."""
        robot = cloud = messages = dropped = 0
        for name, counts in self.counts.items():
            topic = router._topics.get(name)
            if topic is None:
                continue
            if topic.route.publisher == component:
                cloud += counts["bytes_cloud"]
                messages += max(0, counts["messages"] - topic.messages)
                dropped += counts["dropped"]
            row = counts["deliveries"].get(component)
            if row is not None:
                robot += row[2]
                cloud += row[3]
                messages += row[0] + row[1]
                dropped += row[1]
        return robot, cloud, messages, dropped


def link_from_env(skill: str, env: dict[str, str] | None = None) -> CloudLink | None:
    """Return the link to a Skill's cloud relay if BRIDGEOS_CLOUD_RELAY_URL is set; ValueError if it is bad."""
    env = dict(os.environ) if env is None else env
    template = env.get("BRIDGEOS_CLOUD_RELAY_URL", "")
    if not template:
        return None
    url = template.replace("{skill}", skill)
    if not url.startswith(("http://", "https://")):
        raise ValueError(f"BRIDGEOS_CLOUD_RELAY_URL: {template!r} is not an http(s) URL")
    token = env.get("BRIDGEOS_CLOUD_RELAY_TOKEN", "")
    if not token:
        raise ValueError("BRIDGEOS_CLOUD_RELAY_TOKEN is needed with BRIDGEOS_CLOUD_RELAY_URL")
    return CloudLink(url, token)


# --------------------------------------------------------------------------- the process


async def serve(args: argparse.Namespace, config: SkillConfig) -> None:
    """Run a cloud relay until stopped; print one JSON line with its control URL first."""
    settings = RouterSettings(http_host=args.host, http_advertise=args.host, ros_host=args.host)
    relay = CloudRelay(config, ros_master=args.master, token=args.token, settings=settings, robot=args.robot)
    relay.control_port = args.port
    await relay.start()
    print(json.dumps({"url": relay.control_url, "node": relay.node_name, "ros": relay.ros_on}), flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        await relay.close()


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="Run one robot's cloud relay for one Skill.")
    parser.add_argument("--config", required=True, help="the Skill config (JSON file)")
    parser.add_argument("--master", required=True, help="the ROS master the robot's Skill uses")
    parser.add_argument("--host", default="127.0.0.1", help="address to listen on and advertise")
    parser.add_argument("--port", type=int, default=0, help="the control API's port (0: any free one)")
    parser.add_argument("--robot", default=None)
    parser.add_argument("--token", default=os.environ.get("BRIDGEOS_CLOUD_RELAY_TOKEN") or secrets.token_urlsafe(24))
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s %(name)s %(message)s")
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(args, parse_skill_config(json.loads(Path(args.config).read_text()))))


if __name__ == "__main__":
    main()
