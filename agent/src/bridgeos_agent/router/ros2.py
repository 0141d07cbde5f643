"""Route a Skill's ROS 2 topics, services and actions with rclpy (serialized messages, the publisher's QoS).

A topic's router endpoints are made once its first publisher is seen: DDS discovery tells the
publisher's reliability and durability (not its history), and the router mirrors them, so a
best-effort stream stays best-effort and a transient-local ``/map`` reaches late joiners (the
router keeps ``store`` messages, at least 1, for them; volatile topics keep 5000 to ride out bursts).
Services are served on the canonical name and each call goes to the server's active instance;
an action is relayed as its hidden services (``<name>/_action/send_goal``, ``get_result``,
``cancel_goal``) and topics (``<name>/_action/feedback``, ``status``). Cloud instances are
reached in the "cloud" graph when the controller gave one (a client of the robot's Fast DDS
discovery server), else in the robot's graph. rclpy is imported only when a ROS 2 route exists.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from typing import Any

from bridgeos_agent.ros2graph import Ros2Graph, Ros2TypeError, interface_class, rclpy_missing
from bridgeos_agent.rosnames import canonical_name, instance_name
from bridgeos_agent.router.routes import Delivery, RoutedService, RoutedTopic, RouterBase
from bridgeos_agent.router.settings import Where, locations
from bridgeos_agent.skillconfig import ServiceRoute, SkillConfig, TopicRoute

__all__ = ["ACTION_SERVICES", "ACTION_TOPICS", "Ros2Routing", "Ros2Service", "Ros2Topic"]

logger = logging.getLogger(__name__)

# rcl_action's hidden names under an action's name.
ACTION_SERVICES = ("_action/send_goal", "_action/cancel_goal", "_action/get_result")
ACTION_TOPICS = ("_action/feedback", "_action/status")
VOLATILE_DEPTH = 5000
CALL_TIMEOUT = 30.0
RESULT_TIMEOUT = 3600.0  # get_result answers only when the goal ends
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


class Ros2Service(RoutedService):
    """A relayed ROS 2 service: its class, the canonical server and a client per instance."""

    __slots__ = ("clients", "server", "srv_class", "timeout")

    def __init__(self, route: ServiceRoute, srv_class: type, timeout: float) -> None:
        super().__init__(route)
        self.srv_class = srv_class
        self.server: Any = None
        self.clients: dict[str, Any] = {}
        self.timeout = timeout


def _loose_route(kind: Any, **fields: Any) -> Any:
    """Build a route without the config's validation (an action's hidden names and types)."""
    return kind.model_construct(**fields)


class Ros2Routing(RouterBase):
    """The ROS 2 half of the Skill Router."""

    on_route_error: Callable[[str, str], None] | None
    route_errors: dict[str, str]

    def _r2_init(self) -> None:
        self.on_route_error = None  # the integrator turns these into error_message events
        self.route_errors = {}
        self.ros2_off_reason: str | None = None
        self._r2_graphs: tuple[Ros2Graph, Ros2Graph | None] | None = None
        self._r2_sides: dict[str, Any] = {}
        self._r2_services: dict[str, Ros2Service] = {}
        self._r2_statistics: Any = None
        self._r2_task: asyncio.Task[None] | None = None
        self._r2_loop: asyncio.AbstractEventLoop | None = None
        # Instances the controller asked about (placed, waited for): their endpoints open even
        # while inactive; the rest stay closed, for Fast DDS pairs each new endpoint with every
        # endpoint of its participant (the cost of mapping a topic grows with those open).
        self._r2_wanted: set[tuple[str, str]] = set()
        self._r2_cursor = 0
        self._r2_qos_cursor = 0

    def _start_statistics(self) -> None:
        """Start the statistics loop (the router's core does)."""

    # ------------------------------------------------------------------ which routes

    def _speaks_ros2(self, component: str) -> bool:
        config = self.config.components.get(component)
        return config is not None and config.ros_version == 2

    def _ros2_topic_routes(self, config: SkillConfig) -> list[TopicRoute]:
        return [t for t in config.router.topics if self._version(config, t.publisher) == 2]

    def _ros2_service_routes(self, config: SkillConfig) -> list[tuple[ServiceRoute, type, float]]:
        """Return the ROS 2 services to relay, an action's three among them, with their classes."""
        found: list[tuple[ServiceRoute, type, float]] = []
        for route in config.router.services:
            if self._version(config, route.server) == 2:
                srv = self._load(route.name, route.type, "srv")
                if srv is not None:
                    found.append((route, srv, CALL_TIMEOUT))
        for action in config.router.actions:
            cls = self._load(action.name, action.type, "action")
            if cls is None:
                continue
            impl = cls.Impl
            classes = (impl.SendGoalService, impl.CancelGoalService, impl.GetResultService)
            for suffix, srv in zip(ACTION_SERVICES, classes, strict=True):
                name = f"{canonical_name(action.name)}/{suffix}"
                route = _loose_route(ServiceRoute, name=name, type=f"{action.type}:{suffix}", server=action.server)
                found.append((route, srv, RESULT_TIMEOUT if suffix.endswith("get_result") else CALL_TIMEOUT))
        return found

    def _ros2_action_topics(self, config: SkillConfig) -> list[tuple[TopicRoute, type]]:
        found: list[tuple[TopicRoute, type]] = []
        for action in config.router.actions:
            cls = self._load(action.name, action.type, "action")
            if cls is None:
                continue
            impl = cls.Impl
            for suffix, msg in zip(ACTION_TOPICS, (impl.FeedbackMessage, impl.GoalStatusMessage), strict=True):
                name = f"{canonical_name(action.name)}/{suffix}"
                route = _loose_route(
                    TopicRoute, name=name, type=f"{action.type}:{suffix}", publisher=action.server, subscribers=[]
                )
                found.append((route, msg))
        return found

    @staticmethod
    def _version(config: SkillConfig, component: str) -> int:
        found = config.components.get(component)
        return found.ros_version if found is not None else 0

    @property
    def ros2_routes(self) -> bool:
        """Tell whether the Skill has any ROS 2 topic, service or action to route."""
        config = self.config
        return bool(
            config.router.actions
            or any(self._version(config, t.publisher) == 2 for t in config.router.topics)
            or any(self._version(config, s.server) == 2 for s in config.router.services)
        )

    @property
    def ros2_on(self) -> bool:
        """Tell whether ROS 2 routing runs."""
        return bool(self._r2_sides)

    # ------------------------------------------------------------------ errors

    def _route_error(self, name: str, reason: str) -> None:
        """Report a route that cannot run: a log line, ``route_errors`` and the integrator's callback."""
        if self.route_errors.get(name) == reason:
            return
        self.route_errors[name] = reason
        logger.error("skill %s: ROS 2 route %s: %s", self.skill, name, reason)
        if self.on_route_error is not None:
            self.on_route_error(name, reason)

    def _load(self, name: str, type_name: str, kind: Any) -> Any:
        try:
            return interface_class(type_name, kind)
        except Ros2TypeError as exc:
            self._route_error(canonical_name(name), str(exc))
            return None

    # ------------------------------------------------------------------ graphs

    async def set_ros2_graphs(self, robot: Ros2Graph, cloud: Ros2Graph | None = None) -> None:
        """Say which graphs to join: the robot's and, when the cloud runs one, its discovery server's.

        Call again when the cloud's discovery server changes: ROS 2 routing restarts on the new graphs.
        Once a process has made a discovery-server participant, Fast DDS (Jazzy wheels) makes the
        participants made later clients too; each graph's participant is therefore made once per
        process and shared by every Skill (``ros2graphs``), robot first: call this before ``start()``.
        A robot graph never seen before, made after a cloud graph, would hear nothing.
        """
        if self._r2_graphs == (robot, cloud):
            return
        self._r2_graphs = (robot, cloud)
        if self._r2_sides:
            await self._r2_close()
            await self.enable_ros2()

    def _side(self, where: Any) -> Any:
        """Return the graph an instance at ``where`` (None: the canonical name) lives in."""
        if where == "cloud" and "cloud" in self._r2_sides:
            return self._r2_sides["cloud"]
        return self._r2_sides["robot"]

    async def enable_ros2(self) -> bool:
        """Join the ROS 2 graph(s) and route the Skill's ROS 2 routes; say once when it cannot."""
        if self._r2_sides or not self.ros2_routes:
            return bool(self._r2_sides)
        missing = rclpy_missing()
        if missing:
            self.ros2_off_reason = missing
            logger.warning("skill %s: ROS 2 routing is off (%s)", self.skill, missing)
            return False
        from bridgeos_agent.router.ros2graphs import GraphSide

        robot, cloud = self._r2_graphs or (Ros2Graph.from_env(), None)
        base = "router_" + self.skill.replace("-", "_")
        namespace = "/bridgeos"
        sides = {"robot": await asyncio.to_thread(GraphSide, "robot", robot, base, namespace)}
        if cloud is not None and cloud.discovery_server:
            sides["cloud"] = await asyncio.to_thread(GraphSide, "cloud", cloud, base + "_cloud", namespace)
        self._r2_sides = sides
        self._r2_loop = asyncio.get_running_loop()
        self.ros2_off_reason = None
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile

        self._r2_statistics = sides["robot"].node.create_publisher(DiagnosticArray, "/statistics", QoSProfile(depth=10))
        self._r2_add_all(self.config)
        self._r2_task = asyncio.get_running_loop().create_task(self._r2_discover_loop())
        self._start_statistics()
        logger.info(
            "skill %s: routing %d ROS 2 topic(s) and %d service(s) in %s",
            self.skill,
            sum(isinstance(t, Ros2Topic) for t in self._topics.values()),
            len(self._r2_services),
            " and ".join(sides),
        )
        return True

    def _r2_add_all(self, config: SkillConfig) -> None:
        for route in self._ros2_topic_routes(config):
            self._r2_add_topic(route)
        for route, msg in self._ros2_action_topics(config):
            self._r2_add_topic(route, msg)
        for service, srv, timeout in self._ros2_service_routes(config):
            self._r2_add_service(service, srv, timeout)

    async def _r2_close(self) -> None:
        task, self._r2_task = self._r2_task, None
        if task is not None:
            task.cancel()
            await asyncio.gather(task, return_exceptions=True)
        for name in [n for n, t in self._topics.items() if isinstance(t, Ros2Topic)]:
            self._topics.pop(name)
        self._r2_services.clear()
        sides, self._r2_sides = self._r2_sides, {}
        for side in sides.values():
            # Every relay stops before any graph goes: a cloud message must not meet a destroyed robot publisher.
            await asyncio.to_thread(side.relay.close)
        for side in sides.values():
            await asyncio.to_thread(side.close)

    async def _r2_apply(self, old: SkillConfig, new: SkillConfig) -> None:
        """Add, change and remove ROS 2 routes while the router runs."""
        if not self._r2_sides:
            if self.ros2_routes:
                await self.enable_ros2()
            return
        was = {canonical_name(r.name): r for r in self._ros2_topic_routes(old)}
        was.update({canonical_name(r.name): r for r, _ in self._ros2_action_topics(old)})
        now = {canonical_name(r.name): r for r in self._ros2_topic_routes(new)}
        actions = dict((canonical_name(r.name), (r, m)) for r, m in self._ros2_action_topics(new))
        now.update({name: r for name, (r, _) in actions.items()})
        for name, route in was.items():
            if now.get(name) != route:
                self._r2_remove_topic(name)
        for name, route in now.items():
            if was.get(name) != route:
                self._r2_add_topic(route, actions[name][1] if name in actions else None)
        services = {canonical_name(r.name): (r, s, t) for r, s, t in self._ros2_service_routes(new)}
        for name, service in list(self._r2_services.items()):
            if name not in services or services[name][0] != service.route:
                self._r2_remove_service(name)
        for name, (service_route, srv, timeout) in services.items():
            if name not in self._r2_services:
                self._r2_add_service(service_route, srv, timeout)

    # ------------------------------------------------------------------ topics

    def _r2_add_topic(self, route: TopicRoute, msg_class: type | None = None) -> None:
        canonical = canonical_name(route.name)
        if msg_class is None:
            msg_class = self._load(canonical, route.type, "msg")
            if msg_class is None:
                return  # nothing of a route with a bad type is started
        self.route_errors.pop(canonical, None)
        topic = Ros2Topic(route, msg_class, self.clock())
        components = self.config.components
        for subscriber in route.subscribers:
            if subscriber != route.publisher:
                topic.deliveries[subscriber] = Delivery()
        for location in locations(components[route.publisher].location):
            topic.sources[instance_name(route.name, self.skill, route.publisher, location)] = [location, None]
        if topic.deliveries:
            topic.sources[canonical] = [None, None]  # outside publishers reach the subscribers too
        self._topics[canonical] = topic

    def _r2_remove_topic(self, canonical: str) -> None:
        topic = self._topics.get(canonical)
        if not isinstance(topic, Ros2Topic):
            return
        del self._topics[canonical]
        for where, subscription in topic.sources.values():
            if subscription is not None:
                self._side(where).relay.unsubscribe(subscription)
        if topic.canonical_pub is not None:
            self._side(None).relay_node.destroy_publisher(topic.canonical_pub)
        for delivery in topic.deliveries.values():
            for where in ("robot", "cloud"):
                publisher = getattr(delivery, where)
                if publisher is not None:
                    self._side(where).relay_node.destroy_publisher(publisher)

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
                    compatibility, reason = qos_check_compatible(topic.qos, info.qos_profile)
                    if compatibility == QoSCompatibility.ERROR:
                        self._route_error(
                            topic.canonical,
                            f"a subscriber of {name} asks for a QoS the publisher does not offer ({reason}); "
                            "it gets nothing",
                        )

    def _r2_relay(self, topic: Ros2Topic, source: Where | None, data: bytes, info: dict[str, Any]) -> None:
        """Relay one serialized message: the ROS 2 hot path (an executor thread)."""
        payload = len(data)
        active = self._active
        if source is None:
            key = (info.get("publication_sequence_number") or 0, data)
            if key in topic.own:
                del topic.own[key]  # our own canonical publication, heard back
                return
            topic.outside_messages += 1
            for component, delivery in topic.deliveries.items():
                where = active.get(component)
                publisher = getattr(delivery, where) if where is not None else None
                if publisher is None:
                    continue
                publisher.publish(data)
                delivery.messages += 1
                delivery.bytes_robot += payload
        else:
            if active.get(topic.route.publisher) != source:
                return  # the inactive instance's traffic goes nowhere
            store = topic.store
            if store is not None:
                with self._calls_lock:  # a replay to a new subscriber instance is never cut into
                    store.append(data)
                    self._r2_deliver(topic, source, data, payload, active)
            else:
                self._r2_deliver(topic, source, data, payload, active)
        self._r2_window(topic, data, payload, self.clock())

    def _r2_deliver(
        self, topic: Ros2Topic, source: Where, data: bytes, payload: int, active: dict[str, Where | None]
    ) -> None:
        """Send one of the active publisher's messages to the canonical name and the subscribers' instances."""
        topic.messages += 1
        canonical: Any = topic.canonical_pub
        if canonical is not None:
            if topic.deliveries:
                # The canonical subscription hears this back: know it by its sequence number and bytes.
                topic.own[(topic.canonical_delivered + 1, data)] = None
                if len(topic.own) > 10000:
                    topic.own.popitem(last=False)
            canonical.publish(data)
            topic.canonical_delivered += 1
            topic.bytes_robot += payload
        for component, delivery in topic.deliveries.items():
            where = active.get(component)
            publisher = getattr(delivery, where) if where is not None else None
            if publisher is None:
                continue
            publisher.publish(data)
            delivery.messages += 1
            if where == "robot":
                topic.bytes_robot += payload
            else:
                topic.bytes_cloud += payload
            if source == "robot":
                delivery.bytes_robot += payload
            else:
                delivery.bytes_cloud += payload

    @staticmethod
    def _r2_window(topic: Ros2Topic, data: bytes, payload: int, now: float) -> None:
        """Count one relayed message into the statistics window (its period and header stamp's age)."""
        topic.w_messages += 1
        topic.w_bytes += payload
        if topic.w_last:
            period = now - topic.w_last
            topic.w_period_n += 1
            topic.w_period_sum += period
            topic.w_period_sq += period * period
            if period > topic.w_period_max:
                topic.w_period_max = period
        topic.w_last = now
        if topic.has_header and len(data) >= 12 and data[1] == 1:  # CDR little endian: header.stamp first
            sec, nanosec = struct.unpack_from("<iI", data, 4)
            if sec:
                age = time.time() - (sec + nanosec * 1e-9)
                topic.w_age_n += 1
                topic.w_age_sum += age
                topic.w_age_sq += age * age
                if age > topic.w_age_max:
                    topic.w_age_max = age

    # ------------------------------------------------------------------ services

    def _r2_add_service(self, route: ServiceRoute, srv_class: type, timeout: float) -> None:
        service = Ros2Service(route, srv_class, timeout)
        robot = self._side(None)
        service.server = robot.service_node.create_service(
            srv_class,
            service.canonical,
            lambda request, response: self._r2_serve(service, request, response),
            callback_group=robot.group,
        )
        for where in locations(self.config.components[route.server].location):
            side = self._side(where)
            name = instance_name(route.name, self.skill, route.server, where)
            service.clients[where] = side.service_node.create_client(srv_class, name, callback_group=side.group)
        self.route_errors.pop(service.canonical, None)
        self._r2_services[service.canonical] = service

    def _r2_remove_service(self, canonical: str) -> None:
        service = self._r2_services.pop(canonical, None)
        if service is None:
            return
        self._side(None).service_node.destroy_service(service.server)
        for where, client in service.clients.items():
            self._side(where).service_node.destroy_client(client)

    def _r2_serve(self, service: Ros2Service, request: Any, response: Any) -> Any:
        """Answer one call with the active server instance's answer (a service executor thread).

        The call counts as in flight at that instance until it is answered: a switch away waits for it.
        """
        server = service.route.server
        with self._calls_lock:
            where = self._active.get(server)
            if where is not None:
                self._inflight[(server, where)] = self._inflight.get((server, where), 0) + 1
        try:
            return self._r2_call(service, where, request, response)
        finally:
            if where is not None:
                self._leave((server, where), self._r2_loop)

    def _r2_call(self, service: Ros2Service, where: Where | None, request: Any, response: Any) -> Any:
        from rclpy.serialization import serialize_message

        client = service.clients.get(where) if where else None
        if client is None or not client.wait_for_service(timeout_sec=min(5.0, service.timeout)):
            service.errors += 1
            logger.warning("skill %s: %s: no server instance answers (%s)", self.skill, service.canonical, where)
            return response
        done = threading.Event()
        future = client.call_async(request)
        future.add_done_callback(lambda _: done.set())
        if not done.wait(service.timeout) or future.result() is None:
            client.remove_pending_request(future)
            service.errors += 1
            logger.warning("skill %s: %s: the %s instance did not answer", self.skill, service.canonical, where)
            return response
        answer = future.result()
        service.calls += 1
        service.bytes += len(serialize_message(request)) + len(serialize_message(answer))
        return answer

    # ------------------------------------------------------------------ readiness and statistics

    def _r2_ready(self, component: str, location: Where) -> bool:
        """Tell whether a ROS 2 instance's endpoints have matched the router's."""
        if not self._r2_sides:
            return True
        self._r2_want(component, location)
        for topic in list(self._topics.values()):
            if not isinstance(topic, Ros2Topic):
                continue
            route = topic.route
            if route.publisher == component:
                name = instance_name(route.name, self.skill, component, location)
                subscription = topic.sources.get(name, [None, None])[1]
                if subscription is None or not subscription.get_publisher_count():
                    return False
            delivery = topic.deliveries.get(component) if component != route.publisher else None
            if delivery is not None and topic.qos is not None:
                publisher = getattr(delivery, location)
                if publisher is None or not publisher.get_subscription_count():
                    return False
        for service in self._r2_services.values():
            if service.route.server == component:
                client = service.clients.get(location)
                if client is None or not client.service_is_ready():
                    return False
        return True

    def r2_statistics(self) -> dict[str, dict[str, Any]]:
        """Return the ROS 2 services' totals (the topics are in ``statistics()``)."""
        return {
            name: {"kind": "service", "server": s.route.server, "calls": s.calls, "bytes": s.bytes, "errors": s.errors}
            for name, s in self._r2_services.items()
        }

    def _r2_publish_statistics(self, windows: list[Any]) -> None:
        """Publish closed windows on the robot graph's /statistics as diagnostic_msgs/DiagnosticArray."""
        publisher = self._r2_statistics
        if publisher is None or not windows or not publisher.get_subscription_count():
            return
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

        array = DiagnosticArray()
        array.header.stamp = self._r2_sides["robot"].node.get_clock().now().to_msg()
        for window in windows:
            values = [
                KeyValue(key=key, value=str(getattr(window, key)))
                for key in (
                    "node_pub",
                    "node_sub",
                    "window_start",
                    "window_stop",
                    "delivered_msgs",
                    "dropped_msgs",
                    "traffic",
                    "period_mean",
                    "period_stddev",
                    "period_max",
                    "stamp_age_mean",
                    "stamp_age_stddev",
                    "stamp_age_max",
                )
            ]
            array.status.append(
                DiagnosticStatus(level=DiagnosticStatus.OK, name=window.topic, hardware_id=self.skill, values=values)
            )
        publisher.publish(array)


def _type_name(msg_class: type) -> str:
    """Return 'pkg/msg/Type' for a generated class (an action's messages are 'pkg/action/T_...')."""
    module = msg_class.__module__.split(".")
    return f"{module[0]}/{module[1]}/{msg_class.__name__}"
