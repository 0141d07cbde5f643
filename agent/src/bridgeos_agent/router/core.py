"""Run one Skill's router: its life cycle, which instance is active, and config changes."""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import re
import threading
import time
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar, cast

from bridgeos_agent.protocol import Event
from bridgeos_agent.ros2graph import Ros2Graph
from bridgeos_agent.rosnames import canonical_name, instance_name
from bridgeos_agent.rosnode import MasterError, RosNode
from bridgeos_agent.router.http import HttpRouting
from bridgeos_agent.router.ros2 import Ros2Routing
from bridgeos_agent.router.services import ServiceRouting
from bridgeos_agent.router.settings import LOCATIONS, RouterSettings, Where, locations, router_settings_from_env
from bridgeos_agent.router.statistics import STATISTICS_TOPIC, RouterStatistics
from bridgeos_agent.router.topics import TopicRouting
from bridgeos_agent.skillconfig import ServiceRoute, SkillConfig, TopicRoute
from bridgeos_agent.tcpros import TOPIC_STATISTICS_DEFINITION, TOPIC_STATISTICS_MD5, TOPIC_STATISTICS_TYPE

if TYPE_CHECKING:
    from bridgeos_agent.hosts import SkillHost
    from bridgeos_agent.router.cloudlink import CloudLink
    from bridgeos_agent.supervisor import SkillSupervisor

__all__ = ["SkillRouter", "skill_router_plugin"]

logger = logging.getLogger(__name__)

R = TypeVar("R", TopicRoute, ServiceRoute)


class SkillRouter(TopicRouting, ServiceRouting, HttpRouting, RouterStatistics, Ros2Routing):
    """Route one Skill's ROS 1 and ROS 2 topics, services and actions and HTTP requests to its active instances."""

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
        self.node = None
        self.url = None  # the HTTP routes' base URL, when there are any
        self.ros_off_reason: str | None = None
        self._active = {}
        self._containers = {}
        self._topics = {}
        self._services = {}
        self._http = []
        self._http_counts = {}
        self._inflight = {}
        self._drained = {}
        # ROS 2 calls are counted from rclpy's threads: they read the active instance and count
        # themselves under it in one step, so a switch never misses a call still on its way.
        self._calls_lock = threading.Lock()
        self._switching = asyncio.Lock()
        self._statistics = None
        self._last_traffic = {}
        self._runner = None
        self._session = None
        self._tasks: set[asyncio.Task[None]] = set()
        self._ros_warned = False
        self._started = clock()
        # Set before start(): the link to this robot's cloud relay (router/cloudrelay.py), which then
        # delivers the cloud-to-cloud pairs; None: this router relays everything.
        self.cloud_link: CloudLink | None = None
        self._statistics_on = False
        self._r2_init()

    # ------------------------------------------------------------------ life cycle

    @property
    def ros_routes(self) -> bool:
        """Tell whether the Skill has any ROS 1 topic or service to route."""
        return bool(self._ros1_topics(self.config) or self._ros1_services(self.config))

    def _ros1_topics(self, config: SkillConfig) -> list[TopicRoute]:
        return [t for t in config.router.topics if self._version(config, t.publisher) != 2]

    def _ros1_services(self, config: SkillConfig) -> list[ServiceRoute]:
        return [s for s in config.router.services if self._version(config, s.server) != 2]

    @property
    def ros_on(self) -> bool:
        """Tell whether ROS routing runs."""
        return self.node is not None

    async def start(self) -> None:
        """Start HTTP routing (if any routes), ROS 1 routing (if any routes and a master) and ROS 2's."""
        if self.config.router.http:
            await self._start_http()
        if self.ros_routes:
            await self.enable_ros(self.ros_master)
        if self.cloud_link is not None and self.node is not None:
            await self.cloud_link.start(self)
        if self.ros2_routes:
            await self.enable_ros2()

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
        for route in self._ros1_topics(self.config):
            self._add_topic(route)
        for service in self._ros1_services(self.config):
            self._add_service(service)
        errors = await node.settle()
        if errors:
            logger.warning("skill %s: %d ROS registration(s) failed, e.g. %s", self.skill, len(errors), errors[0])
        self._start_statistics()
        logger.info(
            "skill %s: routing %d topic(s) and %d service(s) through %s",
            self.skill,
            len(self._topics),
            len(self._services),
            master,
        )
        return True

    def _start_statistics(self) -> None:
        """Start the one statistics loop (ROS 1 and ROS 2 topics share it)."""
        if not self._statistics_on:
            self._statistics_on = True
            self._spawn(self._statistics_loop())

    def _ros_off(self, reason: str) -> None:
        self.ros_off_reason = reason
        if not self._ros_warned:
            self._ros_warned = True
            logger.warning("skill %s: ROS routing is off (%s); HTTP routing still works", self.skill, reason)

    async def close(self) -> None:
        """Stop routing: unregister from the master, close servers and connections."""
        if self.cloud_link is not None:
            await self.cloud_link.close()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        if self.node is not None:
            node, self.node = self.node, None
            await node.close()
        await self._r2_close()
        await self._stop_http()

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
        if location is not None:
            self._r2_want(component, location)  # type: ignore[arg-type]
        self._active[component] = location  # type: ignore[assignment]
        link = self.cloud_link
        if link is not None and link.up:
            self._spawn(link.handover(self, link.plan(self)))

    async def switch(self, component: str, location: str) -> None:
        """Route to ``location``'s instance from now on; return once the old one's calls have ended."""
        self._check(component, location)
        if location is None:
            raise ValueError("switch needs a location")
        self._r2_want(component, location)  # type: ignore[arg-type]
        # One switch at a time (components moved together): each cloud-relay plan is handed over
        # before the next is made, so an older plan never lands after a newer one.
        async with self._switching:
            with self._calls_lock:
                old = self._active.get(component)
                self._active[component] = location  # type: ignore[assignment]
                key = (component, old)
                busy = old is not None and old != location and bool(self._inflight.get(key))  # type: ignore[arg-type]
                drained = self._drained.setdefault(key, asyncio.Event()) if busy else None  # type: ignore[arg-type]
            link = self.cloud_link
            plan = link.plan(self) if link is not None and link.up else None  # in this same step
            # Topics switch in one step of the event loop: a burst goes wholly to the old or the new
            # instance. Requests and service calls already on their way finish at the old instance.
            if drained is not None:
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(drained.wait(), self.settings.drain_timeout)
            if link is not None and plan is not None:
                await link.handover(self, plan)
        logger.info("skill %s: %s now routed to its %s instance", self.skill, component, location)

    def _check(self, component: str, location: str | None) -> None:
        config = self.config.components.get(component)
        if config is None:
            raise ValueError(f"skill {self.skill!r} has no component {component!r}")
        if location is not None and location not in locations(config.location):
            raise ValueError(f"component {component!r} cannot run on the {location!r}")

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
        if self.cloud_link is not None and not await self.cloud_link.ready(self, component, location):
            return False
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
        if not self._r2_ready(component, location):
            return False
        for http in self._http:
            if http.component == component and not await self._http_answers(http, location):
                return False
        return True

    # ------------------------------------------------------------------ runtime changes

    async def apply(self, config: SkillConfig) -> None:
        """Take a new Skill config: add, change and remove routes while the router runs."""
        old_config = self.config
        self.config = config
        await self._r2_apply(old_config, config)
        if config.router.http:
            await self._start_http()
        else:
            self._http = []
        if self.node is None:
            if self.ros_routes:
                await self.enable_ros(self.ros_master)
            return
        gone, new = _changes(self._ros1_topics(old_config), self._ros1_topics(config))
        for name in gone:
            self._remove_topic(name)
        for route in new:
            self._add_topic(route)
        gone, new_services = _changes(self._ros1_services(old_config), self._ros1_services(config))
        for name in gone:
            self._remove_service(name)
        for service in new_services:
            self._add_service(service)
        errors = await self.node.settle()
        if errors:
            logger.warning("skill %s: %d ROS registration(s) failed, e.g. %s", self.skill, len(errors), errors[0])


def _changes(before: Iterable[R], after: Iterable[R]) -> tuple[list[str], list[R]]:
    """Return the canonical names of the routes gone or changed, and the routes new or changed."""
    was = {canonical_name(route.name): route for route in before}
    now = {canonical_name(route.name): route for route in after}
    gone = [name for name, route in was.items() if now.get(name) != route]
    return gone, [route for name, route in now.items() if was.get(name) != route]


async def skill_router_plugin(supervisor: SkillSupervisor) -> None:
    """Run a Skill's router as a supervisor plug-in (the controller is in the supervisor's context)."""
    controller = cast("SkillHost", supervisor.context["controller"])
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
    from bridgeos_agent.router.cloudlink import CloudLink, link_from_env  # (it builds on this module)

    # The relay the cloud named at login, else the one the environment names, else none.
    offered = getattr(controller, "cloud_relays", {}).get(supervisor.skill)
    try:
        router.cloud_link = CloudLink(offered.url, offered.token) if offered else link_from_env(supervisor.skill)
    except ValueError as exc:
        logger.error(
            "skill %s: no cloud relay (%s); the robot's router relays every link itself", supervisor.skill, exc
        )
    supervisor.context["router"] = router
    graph = getattr(controller, "ros2_graph", None)
    if graph is not None and router.ros2_routes:
        await router.set_ros2_graphs(graph, _cloud_graph(graph, getattr(controller, "ros2_discovery_server", None)))
    router.on_route_error = functools.partial(
        _report_route_error, controller, supervisor.skill, asyncio.get_running_loop()
    )
    try:
        await router.start()
        if router.url:
            _component_env(supervisor)["BRIDGEOS_ROUTER_URL"] = router.url
        supervisor.mark_ready("router")
        config = record.config
        ticks = 0
        while True:
            await asyncio.sleep(1.0)
            if record.config is not config:
                config = record.config
                await router.apply(config)
                if router.url:
                    _component_env(supervisor)["BRIDGEOS_ROUTER_URL"] = router.url
            ticks += 1
            if router.node is None and router.ros_routes and controller.ros_master and ticks % 5 == 0:
                await router.enable_ros(controller.ros_master)
    finally:
        await router.close()


def _cloud_graph(robot: Ros2Graph, server: str | None) -> Ros2Graph | None:
    """Return the robot's cloud graph: the same domain, found through the cloud's discovery server."""
    if not server:
        return None
    return Ros2Graph(domain_id=robot.domain_id, rmw=robot.rmw, discovery_server=server)


def _report_route_error(
    controller: SkillHost, skill: str, loop: asyncio.AbstractEventLoop, name: str, reason: str
) -> None:
    """Tell the cloud about a route that cannot run (its event log shows it); safe from rclpy's threads."""
    data = {"message": f"skill {skill}: route {name}: {reason}"[:2000], "field": "router", "code": "route_failed"}
    tasks = getattr(controller, "tasks", None)
    if tasks is None or loop.is_closed():
        return
    loop.call_soon_threadsafe(lambda: tasks.spawn(controller.emit(Event.ERROR_MESSAGE, data)))


def _component_env(supervisor: SkillSupervisor) -> dict[str, str]:
    """Return the env the supervisor gives the Skill's components (shared through its context)."""
    return cast(dict[str, str], supervisor.context.setdefault("env", {}))
