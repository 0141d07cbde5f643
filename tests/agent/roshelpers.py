"""Run real ROS 1 parts for tests: a private rosmaster and rospy nodes in namespaces."""

from __future__ import annotations

import subprocess
import time
import xmlrpc.client
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from tests.conftest import free_port

HOST_PYTHON = "/usr/bin/python3"  # Debian's interpreter, where rospy lives
NODES = str(Path(__file__).with_name("rosnodes.py"))


def ros_env(master: str, home: Path, namespace: str | None = None) -> dict[str, str]:
    """Return a clean environment for Debian's ROS python, free of the venv."""
    env = {
        "PATH": "/usr/bin:/bin",
        "HOME": str(home),
        "LANG": "C.UTF-8",
        "ROS_MASTER_URI": master,
        "ROS_IP": "127.0.0.1",
        "ROS_HOME": str(home),
        "PYTHONUNBUFFERED": "1",
        "PYTHONWARNINGS": "ignore",
    }
    if namespace:
        env["ROS_NAMESPACE"] = namespace
    return env


@contextmanager
def private_rosmaster(home: Path) -> Iterator[str]:
    """Run a ROS master of the caller's own on a free port, so no other test sees its graph."""
    port = free_port()
    uri = f"http://127.0.0.1:{port}"
    process = subprocess.Popen(
        [HOST_PYTHON, "/usr/bin/rosmaster", "--core", "-p", str(port)],
        env=ros_env(uri, home),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                xmlrpc.client.ServerProxy(uri).getPid("/test")
                break
            except OSError:
                if process.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError("the private rosmaster did not start") from None
                time.sleep(0.1)
        yield uri
    finally:
        process.kill()
        process.wait(10)


class Nodes:
    """Start rospy nodes in namespaces; every one is killed when the test ends."""

    def __init__(self, master: str, home: Path) -> None:
        self.master = master
        self.home = home
        self.processes: list[subprocess.Popen] = []
        self.outputs: dict[str, Path] = {}

    def run(self, key: str, role: str, *args: str, namespace: str | None = None) -> subprocess.Popen:
        """Run one node of tests/agent/rosnodes.py; its stdout goes to a file read with ``lines``."""
        return self.command(key, NODES, role, *args, namespace=namespace)

    def command(self, key: str, *argv: str, namespace: str | None = None) -> subprocess.Popen:
        """Run a ROS program with Debian's python; its stdout goes to a file read with ``lines``."""
        out = self.home / f"{key}.out"
        self.outputs[key] = out
        with out.open("wb") as sink:
            process = subprocess.Popen(
                [HOST_PYTHON, *argv],
                env=ros_env(self.master, self.home, namespace),
                stdout=sink,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        self.processes.append(process)
        return process

    def tool(self, *argv: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
        """Run a ROS command-line tool (rostopic, rosservice) to completion."""
        return subprocess.run(
            [HOST_PYTHON, *argv], env=ros_env(self.master, self.home), capture_output=True, text=True, timeout=timeout
        )

    def lines(self, key: str) -> list[str]:
        """Return what a node printed so far, a line each."""
        return [line for line in self.outputs[key].read_text(errors="replace").splitlines() if line]

    def messages(self, key: str) -> list[tuple[str, int]]:
        """Return the (tag, seq) pairs a listener printed so far."""
        found = []
        for line in self.lines(key):
            parts = line.split()
            if len(parts) == 2 and parts[1].isdigit():
                found.append((parts[0], int(parts[1])))
        return found

    def kill_all(self) -> None:
        for process in self.processes:
            if process.poll() is None:
                process.kill()
            process.wait(10)
