"""Fixtures for the use-case nodes: a private ROS master per module, nodes run by bridgeos-usecase.

Each module gets a rosmaster of its own on a free port (never the shared 11311), so no other
test or engineer sees these topics. Every node runs in its own process group and is stopped,
with all it started, when the test ends, also when it fails.
"""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import BIN, free_port, wait_for_port

ROS_PYTHON = "/usr/bin/python3"


def ros_env(master_uri: str, ros_home: Path, namespace: str | None = None) -> dict[str, str]:
    """Return a clean environment for a ROS process (the venv kept out of it)."""
    env = {
        "PATH": f"/usr/bin:/bin:/usr/sbin:/sbin:{BIN}",
        "HOME": os.environ.get("HOME", "/root"),
        "LANG": "C.UTF-8",
        "ROS_MASTER_URI": master_uri,
        "ROS_IP": "127.0.0.1",
        "ROS_HOME": str(ros_home),
        "PYTHONUNBUFFERED": "1",
    }
    if os.environ.get("PYTHONPATH"):
        env["PYTHONPATH"] = os.environ["PYTHONPATH"]  # the nodes run the code under test (a worktree's)
    if namespace:
        env["ROS_NAMESPACE"] = namespace
    return env


def stop_group(process: subprocess.Popen, timeout: float = 15.0) -> None:
    """Stop a process and everything in its process group: TERM, then KILL."""
    stop_groups([process], timeout)


def stop_groups(processes: list[subprocess.Popen], timeout: float = 15.0) -> None:
    """Stop processes and their process groups: TERM to all at once, then KILL what is left of each.

    The TERMs go out together so the nodes shut down side by side: one by one, a test's
    four rospy nodes took three seconds of teardown (about 0.7 s each to unregister).
    """
    for process in processes:
        if process.poll() is None:
            try:
                os.killpg(process.pid, signal.SIGTERM)
            except ProcessLookupError:
                pass
    deadline = time.monotonic() + timeout
    for process in processes:
        try:
            process.wait(timeout=max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
    for process in processes:
        try:
            os.killpg(process.pid, signal.SIGKILL)  # stragglers of the group, even if the leader is gone
        except ProcessLookupError:
            pass
        process.wait(timeout=timeout)


@dataclass
class RosMaster:
    """A private ROS master on a free port."""

    uri: str
    home: Path


@pytest.fixture(scope="module")
def ros_master(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RosMaster]:
    """Start a rosmaster of the module's own; stop it when the module ends."""
    if not os.access(ROS_PYTHON, os.X_OK) or not Path("/usr/bin/rosmaster").exists():
        pytest.fail("ROS 1 is not installed: run `scripts/services.sh ros` (as root)", pytrace=False)
    home = tmp_path_factory.mktemp("ros")
    port = free_port()
    uri = f"http://127.0.0.1:{port}"
    log = (home / "rosmaster.log").open("wb")
    master = subprocess.Popen(
        [ROS_PYTHON, "/usr/bin/rosmaster", "--core", "-p", str(port)],
        env=ros_env(uri, home),
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    try:
        wait_for_port(port, master, timeout=60)
        yield RosMaster(uri, home)
    finally:
        stop_group(master)
        log.close()


@dataclass
class Nodes:
    """Start use-case nodes with `bridgeos-usecase` and stop them all afterwards."""

    master: RosMaster
    logs: Path
    running: dict[str, subprocess.Popen] = field(default_factory=dict)

    def start(self, label: str, node: str, *args: str, namespace: str | None = None, **env: str) -> None:
        """Start one node; its output goes to a log file named after the label."""
        out = (self.logs / f"{label}.log").open("wb")
        self.running[label] = subprocess.Popen(
            [str(BIN / "bridgeos-usecase"), node, *args],
            env={**ros_env(self.master.uri, self.master.home, namespace), **env},
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        out.close()

    def log(self, label: str) -> str:
        """Return what a node printed so far."""
        return (self.logs / f"{label}.log").read_text(errors="replace")

    def all_logs(self) -> str:
        """Return every node's output, for a failure message."""
        return "\n".join(f"--- {label}\n{self.log(label)[-3000:]}" for label in self.running)

    def wait_for(self, label: str, pattern: str, timeout: float) -> re.Match[str]:
        """Wait until a node prints a line matching a pattern; fail with every log if it never does."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = re.search(pattern, self.log(label))
            if found:
                return found
            for name, process in self.running.items():
                if process.poll() is not None:
                    pytest.fail(f"node {name} exited with {process.returncode}\n{self.all_logs()}")
            time.sleep(0.2)
        pytest.fail(f"{label} did not print /{pattern}/ within {timeout} s\n{self.all_logs()}")

    def probe(self, code: str, *args: str, timeout: float, namespace: str | None = None) -> dict:
        """Run a rospy snippet under the ROS python and return the JSON of its last line."""
        try:
            done = subprocess.run(
                [ROS_PYTHON, "-c", code, *args],
                env=ros_env(self.master.uri, self.master.home, namespace),
                capture_output=True,
                text=True,
                timeout=timeout,
            )
        except subprocess.TimeoutExpired:
            pytest.fail(f"probe hung for {timeout} s\n{self.all_logs()}")
        lines = done.stdout.strip().splitlines()
        if done.returncode != 0 or not lines:
            pytest.fail(f"probe failed ({done.returncode}):\n{done.stderr[-3000:]}\n{self.all_logs()}")
        return json.loads(lines[-1])

    def stop_all(self) -> None:
        """Stop every node this helper started."""
        stop_groups(list(self.running.values()))


@pytest.fixture
def nodes(ros_master: RosMaster, tmp_path: Path) -> Iterator[Nodes]:
    """Give a test a node launcher whose nodes are stopped when it ends."""
    runner = Nodes(ros_master, tmp_path)
    try:
        yield runner
    finally:
        runner.stop_all()


@pytest.fixture
def ros2(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Any, Callable[[str], Any]]]:
    """Give a test a ROS 2 node launcher and listeners in the test graph; stop everything when it ends."""
    from bridgeos_agent.ros2graph import rclpy_missing
    from tests.usecases.ros2help import GRAPH_ENV, Listener, Ros2Nodes

    missing = rclpy_missing()
    if missing:
        pytest.fail(f"ROS 2 is not installed here: {missing} (make install)", pytrace=False)
    for key, value in GRAPH_ENV.items():
        monkeypatch.setenv(key, value)  # an in-process participant reads them when its node is made
    monkeypatch.delenv("ROS_DISCOVERY_SERVER", raising=False)
    (tmp_path / "ros").mkdir(exist_ok=True)
    nodes = Ros2Nodes(tmp_path)
    listeners: list[Listener] = []

    def listener(namespace: str) -> Listener:
        listeners.append(Listener(namespace, nodes))
        return listeners[-1]

    try:
        yield nodes, listener
    finally:
        nodes.stop_all()
        for made in listeners:
            made.close()
