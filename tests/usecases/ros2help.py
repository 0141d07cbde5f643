"""ROS 2 use-case nodes for tests: start them in a test graph, and listen with an in-process rclpy node.

The graph: DDS on loopback only (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in a domain of its own
(BRIDGEOS_TEST_ROS2_DOMAIN, 46 by default), so no other test or engineer sees these topics.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import BIN
from tests.usecases.conftest import stop_groups

GRAPH_ENV = {
    "ROS_DOMAIN_ID": os.environ.get("BRIDGEOS_TEST_ROS2_DOMAIN", "46"),
    "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
    "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
}


def usecase2_command() -> list[str]:
    """Return how to start a ROS 2 use-case node: the installed script, else the module."""
    script = BIN / "bridgeos-usecase2"
    return [str(script)] if script.exists() else [sys.executable, "-m", "bridgeos_agent.usecases.ros2"]


class Ros2Nodes:
    """Start ROS 2 use-case nodes and stop them all afterwards."""

    def __init__(self, logs: Path) -> None:
        self.logs = logs
        self.running: dict[str, subprocess.Popen] = {}

    def env(self, **extra: str) -> dict[str, str]:
        env = {
            "PATH": f"/usr/bin:/bin:{BIN}",
            "HOME": os.environ.get("HOME", "/root"),
            "LANG": "C.UTF-8",
            "PYTHONUNBUFFERED": "1",
            "ROS_LOG_DIR": str(self.logs / "ros"),
            **GRAPH_ENV,
            **extra,
        }
        if os.environ.get("PYTHONPATH"):
            env["PYTHONPATH"] = os.environ["PYTHONPATH"]  # the nodes run the code under test (a worktree's)
        return env

    def start(self, label: str, node: str, *args: str, namespace: str, remap: bool = True) -> None:
        """Start a node in a namespace: by ``__ns`` remap (as the router does) or by ROS_NAMESPACE."""
        ros_args = ["--ros-args", "-r", f"__ns:={namespace}"] if remap else []
        extra = {} if remap else {"ROS_NAMESPACE": namespace}
        with (self.logs / f"{label}.log").open("wb") as out:
            self.running[label] = subprocess.Popen(
                [*usecase2_command(), node, *args, *ros_args],
                env=self.env(**extra),
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def log(self, label: str) -> str:
        return (self.logs / f"{label}.log").read_text(errors="replace")

    def all_logs(self) -> str:
        return "\n".join(f"--- {label}\n{self.log(label)[-3000:]}" for label in self.running)

    def check_alive(self) -> None:
        for name, process in self.running.items():
            if process.poll() is not None:
                pytest.fail(f"node {name} exited with {process.returncode}\n{self.all_logs()}")

    def wait_for(self, label: str, pattern: str, timeout: float) -> re.Match[str]:
        """Wait until a node prints a line matching a pattern."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = re.search(pattern, self.log(label))
            if found:
                return found
            self.check_alive()
            time.sleep(0.2)
        pytest.fail(f"{label} did not print /{pattern}/ within {timeout} s\n{self.all_logs()}")

    def stop_all(self) -> None:
        stop_groups(list(self.running.values()))


class Listener:
    """An rclpy node of this process, in a context of its own, that waits for what the nodes publish."""

    def __init__(self, namespace: str, nodes: Ros2Nodes) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor

        self.nodes = nodes
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(f"probe_{uuid.uuid4().hex[:8]}", namespace=namespace, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)

    def wait_for(self, msg_type: type, topic: str, qos: Any, until: Callable[[Any], bool], timeout: float) -> Any:
        """Return the first message on a topic that satisfies ``until``; fail with every log if none comes."""
        got: list[Any] = []
        subscription = self.node.create_subscription(msg_type, topic, got.append, qos)
        deadline = time.monotonic() + timeout
        last = None
        try:
            while time.monotonic() < deadline:
                self.executor.spin_once(timeout_sec=0.2)
                while got:
                    last = got.pop(0)
                    if until(last):
                        return last
                self.nodes.check_alive()
        finally:
            self.node.destroy_subscription(subscription)
        pytest.fail(f"no fitting message on {topic} within {timeout} s (last: {last})\n{self.nodes.all_logs()}")

    def close(self) -> None:
        import rclpy

        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
