"""Route a Skill's ROS 2 topics, services and actions with rclpy (serialized messages, the publisher's QoS).

Topics are relayed here (the hot path, the statistics windows and the routes' life); their
publishers are found and the router's endpoints opened with the publishers' QoS in
router/ros2discovery.py; services, and an action's hidden services, in router/ros2services.py.
An action is relayed as its hidden services and topics (``<name>/_action/feedback``,
``status``). Cloud instances are reached in the "cloud" graph when the controller gave one (a
client of the robot's Fast DDS discovery server), else in the robot's graph. rclpy is
imported only when a ROS 2 route exists.
"""

from __future__ import annotations

import asyncio
import logging
import struct
import time
from collections.abc import Callable
from typing import Any

from bridgeos_agent.ros2graph import Ros2Graph, Ros2TypeError, interface_class, rclpy_missing
from bridgeos_agent.rosnames import canonical_name, instance_name
from bridgeos_agent.router.ros2discovery import Ros2Discovery, Ros2Topic
from bridgeos_agent.router.ros2services import ACTION_SERVICES, Ros2Service, Ros2ServiceRouting, loose_route
from bridgeos_agent.router.routes import Delivery
from bridgeos_agent.router.settings import Where, locations
from bridgeos_agent.skillconfig import SkillConfig, TopicRoute

__all__ = ["ACTION_SERVICES", "ACTION_TOPICS", "Ros2Routing", "Ros2Service", "Ros2Topic"]

logger = logging.getLogger(__name__)

# rcl_action's hidden topics under an action's name (its services: ros2services.ACTION_SERVICES).
ACTION_TOPICS = ("_action/feedback", "_action/status")


class Ros2Routing(Ros2ServiceRouting, Ros2Discovery):
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

    def _ros2_action_topics(self, config: SkillConfig) -> list[tuple[TopicRoute, type]]:
        found: list[tuple[TopicRoute, type]] = []
        for action in config.router.actions:
            cls = self._load(action.name, action.type, "action")
            if cls is None:
                continue
            impl = cls.Impl
            for suffix, msg in zip(ACTION_TOPICS, (impl.FeedbackMessage, impl.GoalStatusMessage), strict=True):
                name = f"{canonical_name(action.name)}/{suffix}"
                route = loose_route(
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
