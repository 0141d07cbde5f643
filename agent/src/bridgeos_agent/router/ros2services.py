"""Relay a Skill's ROS 2 services, and its actions' hidden services, to the server's active instance.

A service is served on its canonical name in the robot's graph; each call goes to the active
server instance through a client per instance (in the cloud's graph for the cloud instance
when there is one) and counts as in flight there until answered, so a switch away waits for
it. An action is relayed as its three hidden services (``<name>/_action/send_goal``,
``cancel_goal``, ``get_result``) beside its two hidden topics (router/ros2.py).
"""

from __future__ import annotations

import asyncio
import logging
import threading
from typing import TYPE_CHECKING, Any

from bridgeos_agent.rosnames import canonical_name, instance_name
from bridgeos_agent.router.routes import RoutedService, RouterBase
from bridgeos_agent.router.settings import Where, locations
from bridgeos_agent.skillconfig import ServiceRoute, SkillConfig

__all__ = ["ACTION_SERVICES", "Ros2Service", "Ros2ServiceRouting", "loose_route"]

logger = logging.getLogger(__name__)

# rcl_action's hidden services under an action's name.
ACTION_SERVICES = ("_action/send_goal", "_action/cancel_goal", "_action/get_result")
CALL_TIMEOUT = 30.0
RESULT_TIMEOUT = 3600.0  # get_result answers only when the goal ends


class Ros2Service(RoutedService):
    """A relayed ROS 2 service: its class, the canonical server and a client per instance."""

    __slots__ = ("clients", "server", "srv_class", "timeout")

    def __init__(self, route: ServiceRoute, srv_class: type, timeout: float) -> None:
        super().__init__(route)
        self.srv_class = srv_class
        self.server: Any = None
        self.clients: dict[str, Any] = {}
        self.timeout = timeout


def loose_route(kind: Any, **fields: Any) -> Any:
    """Build a route without the config's validation (an action's hidden names and types)."""
    return kind.model_construct(**fields)


class Ros2ServiceRouting(RouterBase):
    """The ROS 2 services of the Skill Router (part of ``Ros2Routing``)."""

    route_errors: dict[str, str]
    _r2_services: dict[str, Ros2Service]
    _r2_loop: asyncio.AbstractEventLoop | None

    if TYPE_CHECKING:  # the rest of Ros2Routing (router/ros2.py)

        def _load(self, name: str, type_name: str, kind: Any) -> Any: ...

        @staticmethod
        def _version(config: SkillConfig, component: str) -> int: ...

        def _side(self, where: Any) -> Any: ...

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
                route = loose_route(ServiceRoute, name=name, type=f"{action.type}:{suffix}", server=action.server)
                found.append((route, srv, RESULT_TIMEOUT if suffix.endswith("get_result") else CALL_TIMEOUT))
        return found

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

    def r2_statistics(self) -> dict[str, dict[str, Any]]:
        """Return the ROS 2 services' totals (the topics are in ``statistics()``)."""
        return {
            name: {"kind": "service", "server": s.route.server, "calls": s.calls, "bytes": s.bytes, "errors": s.errors}
            for name, s in self._r2_services.items()
        }
