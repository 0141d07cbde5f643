"""Join a ROS 2 graph with rclpy: one Context, its router nodes and the threads that spin them."""

from __future__ import annotations

import contextlib
import logging
import os
import re
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from bridgeos_agent.ros2graph import Ros2Graph

__all__ = ["GraphSide", "RelayLoop", "joined"]

logger = logging.getLogger(__name__)

# rmw_fastrtps reads the discovery env when the first node of a Context creates its participant:
# the env is set just around that moment, one graph at a time.
_ENV_LOCK = threading.Lock()
# One Context (one DDS participant) per graph for the life of the process, shared by every Skill's
# router: once a process has a discovery-server client, Fast DDS (Jazzy's wheels) makes participants
# created later clients too, so a robot graph's participant made after the cloud's hears nothing.
# Made once, robot first, and never again, every Skill's router reaches both graphs.
_CONTEXTS: dict[Ros2Graph, Any] = {}


@contextlib.contextmanager
def joined(graph: Ros2Graph) -> Iterator[Any]:
    """Yield the graph's process-wide Context, made on first use, with the graph's env set around it.

    Create a graph's nodes inside this block: rmw reads the discovery env when a Context's first
    node makes its participant. Anything of the process that joins a graph (a Skill's router, the
    rosbridge door) goes through here, so every part shares one participant per graph.
    """
    import rclpy
    from rclpy.context import Context

    env = graph.env()
    env.pop("RMW_IMPLEMENTATION", None)  # chosen once per process, when rclpy loads
    if graph.discovery_server:
        # A plain client of a discovery server learns only the endpoints it matches; the router
        # must see the whole graph to find each instance's publishers, so it is a super client.
        env["ROS_SUPER_CLIENT"] = "TRUE"
    with _ENV_LOCK:
        saved = {name: os.environ.get(name) for name in (*env, "ROS_DISCOVERY_SERVER", "ROS_SUPER_CLIENT")}
        try:
            os.environ.pop("ROS_DISCOVERY_SERVER", None)
            os.environ.pop("ROS_SUPER_CLIENT", None)
            os.environ.update(env)
            context = _CONTEXTS.get(graph)
            if context is None:
                context = _CONTEXTS[graph] = Context()
                rclpy.init(context=context, domain_id=graph.domain_id, args=[])
            yield context
        finally:
            for key, value in saved.items():
                if value is None:
                    os.environ.pop(key, None)
                else:
                    os.environ[key] = value


class GraphSide:
    """One ROS 2 graph the router takes part in: a Context, a topic node and a service node."""

    def __init__(self, label: str, graph: Ros2Graph, node_name: str, namespace: str) -> None:
        import rclpy
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

        self.label = label
        self.graph = graph
        with joined(graph) as context:
            self.context = context
            name = re.sub(r"[^A-Za-z0-9_]", "_", node_name)
            # Topics on one node and executor thread; services on another with a pool, so a
            # long action result never holds up the topics' hot path.
            light: dict[str, Any] = {
                "namespace": namespace,
                "context": self.context,
                "start_parameter_services": False,
            }
            self.node = rclpy.create_node(name, **light)
            self.service_node = rclpy.create_node(name + "_services", **light)
            # The relay's subscriptions: taken by a loop of our own, not rclpy's executor (5-10x faster).
            self.relay_node = rclpy.create_node(name + "_relay", **light, enable_rosout=False)
        self.group = ReentrantCallbackGroup()
        self._executor = SingleThreadedExecutor(context=self.context)
        self._executor.add_node(self.node)
        self._services = MultiThreadedExecutor(num_threads=8, context=self.context)
        self._services.add_node(self.service_node)
        self._threads = [
            threading.Thread(target=self._spin, args=(self._executor,), name=f"ros2-{label}", daemon=True),
            threading.Thread(target=self._spin, args=(self._services,), name=f"ros2-{label}-srv", daemon=True),
        ]
        for thread in self._threads:
            thread.start()
        self.relay = RelayLoop(self.context, self.relay_node, label)

    @staticmethod
    def _spin(executor: Any) -> None:
        from rclpy.executors import ExternalShutdownException

        with contextlib.suppress(ExternalShutdownException):
            executor.spin()

    def close(self) -> None:
        """Leave the graph: stop the threads and destroy the nodes (the shared Context stays)."""
        self.relay.close()
        self._executor.shutdown(timeout_sec=2)
        self._services.shutdown(timeout_sec=2)
        with contextlib.suppress(Exception):
            self.node.destroy_node()
            self.service_node.destroy_node()
            self.relay_node.destroy_node()
        for thread in self._threads:
            thread.join(2)


class RelayLoop:
    """Take serialized messages off the relay's subscriptions and hand them on, in one thread of its own.

    rclpy's executors rebuild their wait set and run a coroutine per message; the hot path needs
    neither: it waits on the subscriptions and drains each ready one with ``take_message``.
    """

    def __init__(self, context: Any, node: Any, label: str) -> None:
        from rclpy.impl.implementation_singleton import rclpy_implementation

        self._rclpy = rclpy_implementation
        self.context = context
        self.node = node
        self._handlers: dict[int, tuple[Any, Callable[[bytes, dict[str, Any]], None]]] = {}
        self._lock = threading.Lock()
        self._changed = True
        self._stop = False
        with context.handle:
            self._guard = rclpy_implementation.GuardCondition(context.handle)
        self._thread = threading.Thread(target=self._run, name=f"ros2-{label}-relay", daemon=True)
        self._thread.start()

    def subscribe(self, msg_class: type, name: str, qos: Any, handler: Callable[[bytes, dict[str, Any]], None]) -> Any:
        """Subscribe ``name`` raw; ``handler(data, info)`` runs in the relay thread for each message."""
        from rclpy.event_handler import SubscriptionEventCallbacks

        quiet = SubscriptionEventCallbacks(use_default_callbacks=False)
        subscription = self.node.create_subscription(msg_class, name, _never, qos, raw=True, event_callbacks=quiet)
        with self._lock:
            self._handlers[subscription.handle.pointer] = (subscription, handler)
            self._changed = True
        self._guard.trigger_guard_condition()
        return subscription

    def unsubscribe(self, subscription: Any) -> None:
        """Stop relaying a subscription and destroy it."""
        with self._lock:
            self._handlers.pop(subscription.handle.pointer, None)
            self._changed = True
        self._guard.trigger_guard_condition()
        self.node.destroy_subscription(subscription)

    def close(self) -> None:
        """Stop the thread."""
        self._stop = True
        with contextlib.suppress(Exception):
            self._guard.trigger_guard_condition()
        self._thread.join(2)

    def _run(self) -> None:
        from rclpy.exceptions import InvalidHandle

        rclpy_ = self._rclpy
        while not self._stop:
            time.sleep(0.02)  # batch a burst of new subscriptions into one rebuild (2,000 topics at once)
            with self._lock:
                entries = list(self._handlers.values())
                self._changed = False
            with contextlib.ExitStack() as stack:
                live: dict[int, tuple[Any, Callable[[bytes, dict[str, Any]], None]]] = {}
                for subscription, handler in entries:
                    try:
                        stack.enter_context(subscription.handle)
                    except InvalidHandle:
                        continue
                    live[subscription.handle.pointer] = (subscription, handler)
                try:
                    stack.enter_context(self._guard)
                    stack.enter_context(self.context.handle)
                except InvalidHandle:
                    return
                wait_set = rclpy_.WaitSet(len(live), 1, 0, 0, 0, 0, self.context.handle)
                while not self._stop and not self._changed:
                    wait_set.clear_entities()
                    for subscription, _ in live.values():
                        wait_set.add_subscription(subscription.handle)
                    wait_set.add_guard_condition(self._guard)
                    try:
                        wait_set.wait(200_000_000)
                    except Exception:  # the context was shut down
                        return
                    for pointer in wait_set.get_ready_entities("subscription"):
                        subscription, handler = live[pointer]
                        take, msg_type = subscription.handle.take_message, subscription.msg_type
                        while True:
                            taken = take(msg_type, True)
                            if taken is None:
                                break
                            try:
                                handler(taken[0], taken[1])
                            except Exception:  # one bad message must not stop the relay
                                logger.exception("relay of %s failed", subscription.topic_name)


def _never(_message: Any) -> None:
    """Stand in for rclpy's callback: the relay loop takes the messages itself."""
