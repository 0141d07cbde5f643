"""Fixtures for end-to-end tests against the real docker engine and ROS master.

A missing service fails the test rather than skipping it: `make test` starts every
service first with scripts/services.sh, so absence means the setup is broken.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
from collections.abc import Iterator
from dataclasses import dataclass, field

import pytest

ROS_MASTER_URI = "http://127.0.0.1:11311"
ROS_IMAGE = "bridgeos/ros:noetic"
# Debian's interpreter, where rospy lives; a venv or pyenv python3 cannot import it.
HOST_ROS_PYTHON = "/usr/bin/python3"
FIX_HINT = "run `scripts/services.sh` (as root) to install and start it"


def _port_open(port: int) -> bool:
    with socket.socket() as sock:
        sock.settimeout(1)
        return sock.connect_ex(("127.0.0.1", port)) == 0


def host_ros_env() -> dict[str, str]:
    """Return a clean environment for Debian's ROS python, free of the venv."""
    return {
        "PATH": "/usr/bin:/bin:/usr/sbin:/sbin",
        "HOME": os.environ.get("HOME", "/root"),
        "LANG": "C.UTF-8",
        "ROS_MASTER_URI": ROS_MASTER_URI,
        "ROS_IP": "127.0.0.1",
        "ROS_HOME": os.environ.get("ROS_HOME", "/var/lib/bridgeos/ros"),
        "PYTHONUNBUFFERED": "1",
    }


@pytest.fixture(scope="session")
def docker_engine() -> str:
    """Return the docker CLI path, failing unless the engine answers."""
    docker = shutil.which("docker")
    if docker is None:
        pytest.fail(f"docker CLI not found: {FIX_HINT}", pytrace=False)
    info = subprocess.run([docker, "info"], capture_output=True, text=True, timeout=30)
    if info.returncode != 0:
        pytest.fail(f"docker engine not reachable ({info.stderr.strip()[:200]}): {FIX_HINT}", pytrace=False)
    return docker


@pytest.fixture(scope="session")
def ros_image(docker_engine: str) -> str:
    """Return the ROS image tag, failing unless it is built."""
    found = subprocess.run([docker_engine, "image", "inspect", ROS_IMAGE], capture_output=True, timeout=30)
    if found.returncode != 0:
        pytest.fail(f"image {ROS_IMAGE} not built: run `scripts/services.sh images`", pytrace=False)
    return ROS_IMAGE


@dataclass
class HostRos:
    """Run code with the host's Debian python, which has rospy, against the ROS master."""

    master_uri: str

    def python(self, code: str, *args: str, timeout: float) -> subprocess.CompletedProcess[str]:
        """Run `code` with `args` in a clean ROS environment and capture its output."""
        return subprocess.run(
            [HOST_ROS_PYTHON, "-c", code, *args],
            env=host_ros_env(),
            capture_output=True,
            text=True,
            timeout=timeout,
        )


@pytest.fixture(scope="session")
def host_ros() -> HostRos:
    """Return the host ROS runner, failing unless roscore and host rospy are usable."""
    if not _port_open(11311):
        pytest.fail(f"no ROS master on {ROS_MASTER_URI}: {FIX_HINT}", pytrace=False)
    ros = HostRos(ROS_MASTER_URI)
    probe = ros.python("import rospy, std_msgs.msg", timeout=30)
    if probe.returncode != 0:
        pytest.fail(f"host rospy not importable by {HOST_ROS_PYTHON}: {FIX_HINT}", pytrace=False)
    return ros


@dataclass
class Containers:
    """Run detached containers and remove every one of them afterwards."""

    docker: str
    names: list[str] = field(default_factory=list)

    def run(self, name: str, image: str, *command: str, env: dict[str, str] | None = None) -> str:
        """Start a detached host-network container and return its name."""
        args = [self.docker, "run", "-d", "--rm", "--init", "--network", "host", "--name", name]
        for key, value in (env or {}).items():
            args += ["-e", f"{key}={value}"]
        self.names.append(name)
        subprocess.run([*args, image, *command], check=True, capture_output=True, text=True, timeout=60)
        return name

    def logs(self, name: str) -> str:
        """Return what the container printed so far."""
        out = subprocess.run([self.docker, "logs", name], capture_output=True, text=True, timeout=30)
        return out.stdout + out.stderr

    def remove_all(self) -> None:
        """Force-remove every container this helper started."""
        for name in self.names:
            subprocess.run([self.docker, "rm", "-f", name], capture_output=True, timeout=60)


@pytest.fixture
def containers(docker_engine: str) -> Iterator[Containers]:
    """Give a test a container runner whose containers are removed when it ends."""
    runner = Containers(docker_engine)
    try:
        yield runner
    finally:
        runner.remove_all()
