"""A robot's ROS 2 graph: how its nodes find each other, and the env that puts a component in it.

On the robot, ROS 2 nodes discover each other the usual way (multicast, kept to
``discovery_range``) in the robot's ``domain_id``. Multicast does not cross a VPN tunnel or
the internet, so the cloud runs one Fast DDS discovery server per robot: the robot's cloud
copies and the cloud side of its router are clients of that server and nothing else, which
keeps every robot's cloud graph apart from every other's on shared hosts without spending a
``ROS_DOMAIN_ID`` per robot (a host has about 230 of those).
"""

from __future__ import annotations

import importlib
import os
import shutil
import sys
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

__all__ = [
    "DEFAULT_RMW",
    "DISCOVERY_RANGES",
    "Ros2Graph",
    "Ros2TypeError",
    "discovery_server_command",
    "fastdds_library_path",
    "interface_class",
    "namespace_arguments",
    "rclpy_missing",
]

DEFAULT_RMW = "rmw_fastrtps_cpp"
DISCOVERY_RANGES = ("OFF", "LOCALHOST", "SUBNET", "SYSTEM_DEFAULT")
Kind = Literal["msg", "srv", "action"]


class Ros2TypeError(LookupError):
    """A ROS 2 interface type that cannot be loaded, with the reason."""


@dataclass(frozen=True)
class Ros2Graph:
    """Where a ROS 2 node of one robot finds its peers."""

    domain_id: int = 0
    rmw: str = DEFAULT_RMW
    discovery_range: str = "LOCALHOST"
    static_peers: tuple[str, ...] = field(default=())
    # "host:port" of the robot's discovery server in the cloud; when set, discovery is unicast only.
    discovery_server: str | None = None

    def __post_init__(self) -> None:
        if not 0 <= self.domain_id <= 232:
            raise ValueError(f"ROS_DOMAIN_ID must be 0..232, not {self.domain_id}")
        if self.discovery_range not in DISCOVERY_RANGES:
            raise ValueError(f"discovery range must be one of {', '.join(DISCOVERY_RANGES)}")

    def env(self) -> dict[str, str]:
        """Return the environment that puts a ROS 2 process in this graph."""
        env = {"ROS_DOMAIN_ID": str(self.domain_id), "RMW_IMPLEMENTATION": self.rmw}
        if self.discovery_server:
            env["ROS_DISCOVERY_SERVER"] = self.discovery_server
        else:
            env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = self.discovery_range
            if self.static_peers:
                env["ROS_STATIC_PEERS"] = ";".join(self.static_peers)
        return env

    def as_dict(self) -> dict[str, Any]:
        """Return the graph as plain JSON data (the API and the dashboard show it)."""
        data = asdict(self)
        data["static_peers"] = list(self.static_peers)
        return data

    @classmethod
    def from_env(cls, env: Mapping[str, str] = os.environ) -> Ros2Graph:
        """Read the graph a process was started in from its ROS 2 environment."""
        return cls(
            domain_id=int(env.get("ROS_DOMAIN_ID") or 0),
            rmw=env.get("RMW_IMPLEMENTATION") or DEFAULT_RMW,
            discovery_range=env.get("ROS_AUTOMATIC_DISCOVERY_RANGE") or "LOCALHOST",
            static_peers=tuple(p for p in (env.get("ROS_STATIC_PEERS") or "").split(";") if p),
            discovery_server=env.get("ROS_DISCOVERY_SERVER") or None,
        )


def namespace_arguments(namespace: str) -> list[str]:
    """Return the ``--ros-args`` that push a ROS 2 node into the namespace the router assigned."""
    return ["--ros-args", "-r", f"__ns:={namespace}"]


def rclpy_missing() -> str | None:
    """Return why rclpy cannot be used in this Python, or None when it can."""
    try:
        importlib.import_module("rclpy")
    except ImportError as exc:
        return f"rclpy is not installed ({exc}); pip install 'bridgeos-agent[ros2]'"
    return None


def interface_class(type_name: str, kind: Kind = "msg") -> type:
    """Load a ROS 2 message, service or action class from 'pkg/Type' or 'pkg/kind/Type'."""
    parts = type_name.split("/")
    if len(parts) == 2:
        package, name = parts
    elif len(parts) == 3 and parts[1] == kind:
        package, name = parts[0], parts[2]
    else:
        raise Ros2TypeError(f"{type_name!r} is not a ROS 2 {kind} type ('package/{kind}/Type')")
    try:
        module = importlib.import_module(f"{package}.{kind}")
    except ImportError:
        raise Ros2TypeError(f"the interface package {package!r} is not installed (needed for {type_name!r})") from None
    cls = getattr(module, name, None)
    if not isinstance(cls, type):
        raise Ros2TypeError(f"{package!r} has no {kind} {name!r}")
    return cls


def fastdds_library_path() -> str:
    """Return the directories Fast DDS's own tools need on ``LD_LIBRARY_PATH`` (the wheels bundle them)."""
    prefix = Path(sys.prefix)
    site = prefix / "lib" / f"python{sys.version_info.major}.{sys.version_info.minor}" / "site-packages"
    dirs = [prefix / "lib", *sorted(site.glob("ros_fastrtps*.libs"))]
    return os.pathsep.join(str(d) for d in dirs if d.is_dir())


def discovery_server_command(host: str, port: int, *, server_id: int = 0) -> tuple[list[str], dict[str, str]]:
    """Return the command and extra env that run a Fast DDS discovery server on ``host:port``."""
    binary = shutil.which("fast-discovery-server", path=str(Path(sys.prefix) / "bin")) or shutil.which(
        "fast-discovery-server"
    )
    if binary is None:
        raise FileNotFoundError("fast-discovery-server is not installed; pip install 'bridgeos-agent[ros2]'")
    library = fastdds_library_path()
    old = os.environ.get("LD_LIBRARY_PATH")
    env = {"LD_LIBRARY_PATH": os.pathsep.join(p for p in (library, old) if p)}
    return [binary, "-i", str(server_id), "-l", host, "-p", str(port)], env
