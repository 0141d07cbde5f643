"""Join a ROS 2 graph with rclpy: one Context, its router nodes and the threads that spin them."""

from __future__ import annotations

import contextlib
import os
import re
import threading
from typing import Any

from bridgeos_agent.ros2graph import Ros2Graph

__all__ = ["GraphSide"]

# rmw_fastrtps reads the discovery env when the first node of a Context creates its participant:
# the env is set just around that moment, one graph at a time.
_ENV_LOCK = threading.Lock()


class GraphSide:
    """One ROS 2 graph the router takes part in: a Context, a topic node and a service node."""

    def __init__(self, label: str, graph: Ros2Graph, node_name: str, namespace: str) -> None:
        import rclpy
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.context import Context
        from rclpy.executors import MultiThreadedExecutor, SingleThreadedExecutor

        self.label = label
        self.graph = graph
        self.context = Context()
        env = graph.env()
        env.pop("RMW_IMPLEMENTATION", None)  # chosen once per process, when rclpy loads
        with _ENV_LOCK:
            saved = {name: os.environ.get(name) for name in (*env, "ROS_DISCOVERY_SERVER")}
            try:
                os.environ.pop("ROS_DISCOVERY_SERVER", None)
                os.environ.update(env)
                rclpy.init(context=self.context, domain_id=graph.domain_id, args=[])
                name = re.sub(r"[^A-Za-z0-9_]", "_", node_name)
                # Topics on one node and executor thread; services on another with a pool, so a
                # long action result never holds up the topics' hot path.
                self.node = rclpy.create_node(name, namespace=namespace, context=self.context)
                self.service_node = rclpy.create_node(name + "_services", namespace=namespace, context=self.context)
            finally:
                for key, value in saved.items():
                    if value is None:
                        os.environ.pop(key, None)
                    else:
                        os.environ[key] = value
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

    @staticmethod
    def _spin(executor: Any) -> None:
        from rclpy.executors import ExternalShutdownException

        with contextlib.suppress(ExternalShutdownException):
            executor.spin()

    def close(self) -> None:
        """Leave the graph: stop the threads and destroy the nodes and the Context."""
        self._executor.shutdown(timeout_sec=2)
        self._services.shutdown(timeout_sec=2)
        with contextlib.suppress(Exception):
            self.node.destroy_node()
            self.service_node.destroy_node()
        with contextlib.suppress(Exception):
            self.context.try_shutdown()
        for thread in self._threads:
            thread.join(2)
