"""The robot router's link to its Skill's cloud relay (router/cloudrelay.py).

Through a :class:`CloudLink` the robot's router hands the relay the (topic, subscriber) pairs
whose publisher and subscriber are both active in the cloud, stops relaying them and stops
subscribing to a cloud publisher nobody on the robot needs, so their bytes no longer cross the
robot's link (twice). The robot's router stays the authority on which instance is active: it
sends its whole map with every handover, polls the relay's totals into its own statistics, and
relays everything itself again, saying so once in its log, when the relay stops answering.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import time
from typing import TYPE_CHECKING, Any

import aiohttp

from bridgeos_agent.rosnames import instance_name
from bridgeos_agent.rostopics import Subscription
from bridgeos_agent.router.handover import AWAY, HOLD, QUIET_S, FrameLog, Pair, cloud_pairs, drained, start_after
from bridgeos_agent.router.routes import RoutedTopic
from bridgeos_agent.router.settings import Where

if TYPE_CHECKING:
    from bridgeos_agent.router.core import SkillRouter
    from bridgeos_agent.router.routes import RouterBase

__all__ = ["CloudLink", "link_from_env"]

logger = logging.getLogger(__name__)

KEEP_S = 5.0  # a cloud source subscribed for a readiness check is kept this long
FAILURES = 3  # polls in a row without an answer before the robot takes every pair back


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
