"""Find a Skill's ROS 2 publishers and open the router's endpoints with the QoS they offer.

A topic's router endpoints are made once its first publisher is seen: DDS discovery tells the
publisher's reliability and durability (not its history), and the router mirrors them, so a
best-effort stream stays best-effort and a transient-local ``/map`` reaches late joiners (the
router keeps ``store`` messages, at least 1, for them; volatile topics keep 5000 to ride out
bursts). Only the instances that are active or that the controller asked about get endpoints:
Fast DDS pairs each new endpoint with every endpoint of its participant.
"""

from __future__ import annotations

import asyncio
import logging
from collections import OrderedDict, deque
from typing import TYPE_CHECKING, Any

from bridgeos_agent.rosnames import instance_name
from bridgeos_agent.router.routes import Delivery, RoutedTopic, RouterBase
from bridgeos_agent.router.settings import Where, locations
from bridgeos_agent.skillconfig import TopicRoute

__all__ = ["Ros2Discovery", "Ros2Topic"]

logger = logging.getLogger(__name__)

VOLATILE_DEPTH = 5000
PER_PASS = 64  # graph lookups per discovery pass (every 50 ms)


class Ros2Topic(RoutedTopic):
    """A routed ROS 2 topic: its type, the sources seen so far and the QoS mirrored."""

    __slots__ = ("matched", "msg_class", "own", "qos", "sources")

    def __init__(self, route: TopicRoute, msg_class: type, now: float) -> None:
        super().__init__(route, None, now)
        self.msg_class = msg_class
        self.qos: Any = None  # the QoS of the router's publications, from the first publisher seen
        self.sources: dict[str, list[Any]] = {}  # name -> [where or None, subscription or None]
        self.own: OrderedDict[tuple[int, bytes], None] = OrderedDict()  # what we sent on the canonical name
        self.matched: dict[tuple[str, str], int] = {}  # (subscriber, where) -> readers its sink matched, last seen
        fields = list(msg_class.get_fields_and_field_types().values())  # type: ignore[attr-defined]
        self.has_header = bool(fields) and fields[0] == "std_msgs/Header"


def _type_name(msg_class: type) -> str:
    """Return 'pkg/msg/Type' for a generated class (an action's messages are 'pkg/action/T_...')."""
    module = msg_class.__module__.split(".")
    return f"{module[0]}/{module[1]}/{msg_class.__name__}"


class Ros2Discovery(RouterBase):
    """The ROS 2 discovery of the Skill Router (part of ``Ros2Routing``): sources, sinks and their QoS."""

    _r2_sides: dict[str, Any]
    _r2_wanted: set[tuple[str, str]]
    _r2_cursor: int
    _r2_qos_cursor: int

    if TYPE_CHECKING:  # the rest of Ros2Routing (router/ros2.py)

        def _side(self, where: Any) -> Any: ...

        def _route_error(self, name: str, reason: str) -> None: ...

        def _r2_relay(self, topic: Ros2Topic, source: Where | None, data: bytes, info: dict[str, Any]) -> None: ...

    async def _r2_discover_loop(self) -> None:
        passes = 0
        while True:
            passes += 1
            try:
                self._r2_discover()
                self._r2_replay()
                if passes % 4 == 0:
                    self._r2_check_qos()
            except Exception:  # one bad graph answer must not end routing
                logger.exception("skill %s: ROS 2 discovery pass failed", self.skill)
            await asyncio.sleep(0.05)

    def _r2_discover(self) -> None:
        """Subscribe each source once a publisher shows up there, mirroring its QoS.

        A name present in the graph is asked about its publishers (a graph-wide lookup), at most
        ``PER_PASS`` names a pass: a canonical name stays present through the router's own
        publisher, and asking about all of them every pass would cost O(topics x endpoints).
        """
        names: dict[int, set[str]] = {}
        instances: list[tuple[Ros2Topic, str, list[Any], Any]] = []
        canonicals: list[tuple[Ros2Topic, str, list[Any], Any]] = []
        for topic in list(self._topics.values()):
            if not isinstance(topic, Ros2Topic):
                continue
            for name, source in topic.sources.items():
                if source[1] is not None:
                    continue
                side = self._side(source[0])
                present = names.get(id(side))
                if present is None:
                    present = names[id(side)] = {n for n, _ in side.node.get_topic_names_and_types()}
                if name in present:
                    (canonicals if source[0] is None else instances).append((topic, name, source, side))
        # An instance's publisher is what a placement waits for: those first, then a turn of the rest.
        found = instances + canonicals
        if len(found) > PER_PASS:
            start = self._r2_cursor % len(found)
            found = (found[start:] + found[:start])[:PER_PASS]
            self._r2_cursor = start + PER_PASS
        for topic, name, source, side in found:
            if source[1] is None:
                self._r2_try_source(topic, name, source, side)

    def _r2_replay(self) -> None:
        """Give a subscriber instance that just connected the topic's stored messages (state sync, as ROS 1's).

        Its sink had no reader before: nobody else hears them twice. Under the calls lock, which the
        relay holds for a topic with a store, so no live message slips in between or out.
        """
        for topic in list(self._topics.values()):
            if not isinstance(topic, Ros2Topic) or topic.store is None or topic.qos is None:
                continue
            for component, delivery in topic.deliveries.items():
                for where in ("robot", "cloud"):
                    publisher = getattr(delivery, where)
                    if publisher is None:
                        continue
                    count = publisher.get_subscription_count()
                    if count and not topic.matched.get((component, where)) and topic.store:
                        with self._calls_lock:
                            for data in topic.store:
                                publisher.publish(data)
                    topic.matched[(component, where)] = count

    def _r2_try_source(self, topic: Ros2Topic, name: str, source: list[Any], side: Any) -> None:
        infos = side.node.get_publishers_info_by_topic(name)
        own = side.node.get_name()
        infos = [i for i in infos if i.node_name not in (own, own + "_services", own + "_relay")]
        if not infos:
            return
        info = infos[0]
        wanted = _type_name(topic.msg_class)
        if info.topic_type != wanted:
            self._route_error(topic.canonical, f"{name} is published as {info.topic_type}, the route says {wanted}")
            return
        self._r2_subscribe(topic, name, source, info.qos_profile.reliability, info.qos_profile.durability)

    def _r2_open(self, topic: Ros2Topic, reliability: Any, durability: Any) -> None:
        """Open a topic's endpoints as when its wanted instances' publishers of this QoS show up."""
        publisher = topic.route.publisher
        for name, source in topic.sources.items():
            if source[1] is None and source[0] is not None and self._r2_wants(publisher, source[0]):
                self._r2_subscribe(topic, name, source, reliability, durability)

    def _r2_wants(self, component: str, where: Where) -> bool:
        """Tell whether an instance's endpoints should be open: it is active or the controller asked for it."""
        return self._active.get(component) == where or (component, where) in self._r2_wanted

    def _r2_want(self, component: str, where: Where) -> None:
        """Open the endpoints that deliver to an instance (it is placed, waited for or switched to)."""
        if (component, where) in self._r2_wanted:
            return
        self._r2_wanted.add((component, where))
        if not self._r2_sides:
            return
        for topic in list(self._topics.values()):
            if isinstance(topic, Ros2Topic) and topic.qos is not None:
                delivery = topic.deliveries.get(component)
                if delivery is not None and getattr(delivery, where) is None:
                    self._r2_make_sink(topic, component, delivery, where)

    def _r2_subscribe(self, topic: Ros2Topic, name: str, source: list[Any], reliability: Any, durability: Any) -> None:
        """Subscribe one source with the QoS its publisher offers (the sinks too, for the first)."""
        from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile

        where = source[0]
        durable = durability == DurabilityPolicy.TRANSIENT_LOCAL
        qos = QoSProfile(
            history=HistoryPolicy.KEEP_LAST,
            depth=max(1, topic.route.store) if durable else VOLATILE_DEPTH,
            reliability=reliability,
            durability=durability,
        )
        if topic.qos is None:
            topic.qos = qos
            if durable and topic.store is None:
                topic.store = deque(maxlen=1)  # a latched message reaches a moved subscriber too
            self._r2_make_sinks(topic)
        if not durable:
            # The router's own reader keeps all: falling behind in a burst must not cost messages.
            qos = QoSProfile(history=HistoryPolicy.KEEP_ALL, reliability=reliability, durability=durability)
        source[1] = self._side(where).relay.subscribe(
            topic.msg_class,
            name,
            qos,
            lambda data, msg_info, topic=topic, where=where: self._r2_relay(topic, where, data, msg_info),
        )
        if where is not None:
            topic.node_pub = name

    def _r2_make_sinks(self, topic: Ros2Topic) -> None:
        from rclpy.event_handler import PublisherEventCallbacks

        # On the relay's node, which no executor spins: an executor would walk every publisher's
        # event handlers each time an endpoint is added (quadratic at thousands of topics).
        quiet = PublisherEventCallbacks(use_default_callbacks=False)
        robot = self._side(None).relay_node
        topic.canonical_pub = robot.create_publisher(topic.msg_class, topic.canonical, topic.qos, event_callbacks=quiet)
        for component, delivery in topic.deliveries.items():
            for where in locations(self.config.components[component].location):
                if self._r2_wants(component, where):
                    self._r2_make_sink(topic, component, delivery, where)

    def _r2_make_sink(self, topic: Ros2Topic, component: str, delivery: Delivery, where: Where) -> None:
        """Publish a topic into one subscriber instance's namespace, with the publisher's QoS."""
        from rclpy.event_handler import PublisherEventCallbacks

        quiet = PublisherEventCallbacks(use_default_callbacks=False)
        name = instance_name(topic.route.name, self.skill, component, where)
        node = self._side(where).relay_node
        setattr(delivery, where, node.create_publisher(topic.msg_class, name, topic.qos, event_callbacks=quiet))

    def _r2_check_qos(self) -> None:
        """Report subscribers that ask for a QoS the router's publication (the publisher's) does not offer.

        ``PER_PASS`` topics a call, in turn: counting a name's subscribers walks the whole graph.
        """
        from rclpy.qos import QoSCompatibility, qos_check_compatible

        opened = [t for t in self._topics.values() if isinstance(t, Ros2Topic) and t.qos is not None]
        if len(opened) > PER_PASS:
            start = self._r2_qos_cursor % len(opened)
            opened = (opened[start:] + opened[:start])[:PER_PASS]
            self._r2_qos_cursor = start + PER_PASS
        for topic in opened:
            sinks: list[tuple[Any, Any]] = [(None, topic.canonical_pub)]
            for delivery in topic.deliveries.values():
                sinks += [(where, getattr(delivery, where)) for where in ("robot", "cloud")]
            for where, publisher in sinks:
                if publisher is None:
                    continue
                node = self._side(where).relay_node
                name = publisher.topic_name
                if publisher.get_subscription_count() >= node.count_subscribers(name):
                    continue  # every subscriber matched
                for info in node.get_subscriptions_info_by_topic(name):
                    compatibility, reason = qos_check_compatible(topic.qos, _as_asked(info.qos_profile))
                    if compatibility == QoSCompatibility.ERROR:
                        self._route_error(
                            topic.canonical,
                            f"a subscriber of {name} asks for a QoS the publisher does not offer ({reason}); "
                            "it gets nothing",
                        )


def _as_asked(profile: Any) -> Any:
    """Return a subscriber's QoS as it asked: the graph reports an unset deadline or lease as Infinite.

    Checked as they come, every subscriber that asked for no deadline would be "incompatible" with a
    publisher that offers none (found on a loaded machine, where a subscriber was not matched yet).
    """
    from rclpy.duration import Duration, Infinite

    for field in ("deadline", "lifespan", "liveliness_lease_duration"):
        if getattr(profile, field) == Infinite:
            setattr(profile, field, Duration())
    return profile
