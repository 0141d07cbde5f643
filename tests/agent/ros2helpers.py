"""Run real rclpy nodes (tests/agent/ros2nodes.py) in subprocesses kept to one ROS 2 graph."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from bridgeos_agent.ros2graph import Ros2Graph, namespace_arguments

NODES = str(Path(__file__).with_name("ros2nodes.py"))


def test_graph() -> Ros2Graph:
    """Return the graph of this run: loopback only, the domain of ROS_DOMAIN_ID (44 by default)."""
    return Ros2Graph(domain_id=int(os.environ.get("ROS_DOMAIN_ID") or 44), discovery_range="LOCALHOST")


class Ros2Nodes:
    """Start ros2nodes.py roles and read what they print."""

    def __init__(self, graph: Ros2Graph, directory: Path) -> None:
        self.graph = graph
        self.directory = directory
        self.processes: dict[str, subprocess.Popen[bytes]] = {}

    def run(self, key: str, role: str, *args: str, namespace: str | None = None, graph: Ros2Graph | None = None) -> None:
        env = {**os.environ, **(graph or self.graph).env(), "PYTHONUNBUFFERED": "1"}
        env.pop("ROS_DISCOVERY_SERVER", None) if graph is None else None
        command = [sys.executable, NODES, role, *args, *(namespace_arguments(namespace) if namespace else [])]
        out = (self.directory / f"{key}.out").open("wb")
        self.processes[key] = subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT)

    def lines(self, key: str) -> list[str]:
        path = self.directory / f"{key}.out"
        return path.read_text(errors="replace").splitlines() if path.exists() else []

    def messages(self, key: str) -> list[tuple[str, int]]:
        found = []
        for line in self.lines(key):
            parts = line.split()
            if len(parts) == 3 and parts[1].isdigit():
                found.append((parts[0], int(parts[1])))
        return found

    def stop(self, key: str) -> None:
        process = self.processes.pop(key)
        process.kill()
        process.wait(10)

    def kill_all(self) -> None:
        for key in list(self.processes):
            self.stop(key)
