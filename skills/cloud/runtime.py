"""The cloud side of the runtime interface: what the orchestration needs from swarm, docker and process.

Every cloud runtime is the agent's `Runtime` (start, stop, status, logs, stats, get_state,
load_state, close) plus a few things only the cloud does: a network per robot, a ROS master
and a ROS 2 discovery server per robot, the address and published ports robots reach a copy at, a restart, and an
inventory of everything this cloud runs (so the reconciler can restart the crashed and
remove orphans).

The cloud runtimes never restart anything by themselves (their restart policy allows no
restarts): the reconciler decides, so every restart is counted, logged and backed off in
one place, whichever worker process launched the copy.

Names and labels: every object carries ``io.bridgeos.cloud=<cloud id>`` (so clouds sharing an
engine never touch each other's objects), the robot, skill and component, and its kind
(``component``, ``ros-master`` or ``ros2-discovery``). Names are at most 63 characters (a DNS label, as Swarm
requires): a readable prefix and a hash of the whole identity, so two long ids never collide.
"""

from __future__ import annotations

import hashlib
import re
from abc import abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from django.conf import settings
from django.db import connections

from bridgeos_agent.runtime.base import ComponentSpec, ComponentState, RestartPolicy, Runtime, RuntimeFailure, Status
from bridgeos_cloud.env import ConfigError

__all__ = [
    "KIND_COMPONENT",
    "KIND_ROS2_DISCOVERY",
    "KIND_ROS_MASTER",
    "NO_RESTARTS",
    "RUNTIMES",
    "CloudRuntime",
    "CloudSpec",
    "EngineBusy",
    "Observed",
    "cloud_id",
    "discovery_address",
    "object_name",
    "runtime_name",
]

RUNTIMES = ("swarm", "docker", "process")
KIND_COMPONENT = "component"
KIND_ROS_MASTER = "ros-master"
KIND_ROS2_DISCOVERY = "ros2-discovery"
MASTER_COMPONENT = "rosmaster"  # the component id a robot's ROS master is known by in labels
DISCOVERY_COMPONENT = "ros2discovery"  # and its ROS 2 discovery server's

LABEL_CLOUD = "io.bridgeos.cloud"
LABEL_ROBOT = "io.bridgeos.robot"
LABEL_SKILL = "io.bridgeos.skill"
LABEL_COMPONENT = "io.bridgeos.component"
LABEL_KIND = "io.bridgeos.kind"
LABEL_TOKEN = "io.bridgeos.token"
LABEL_LOCATION = "io.bridgeos.location"

# The cloud copies never restart on their own: the reconciler does it (see the module docstring).
NO_RESTARTS = RestartPolicy(max_restarts=0)

_UNSAFE = re.compile(r"[^a-z0-9-]+")


def cloud_id() -> str:
    """Return this cloud's id: BRIDGEOS_CLOUD_ID, else one derived from the database it uses."""
    configured = settings.BRIDGEOS["CLOUD_ID"]
    if configured:
        return configured
    # Read at call time: a test run renames the database after settings are loaded.
    db = connections["default"].settings_dict
    identity = f"{db.get('HOST') or ''}:{db.get('PORT') or ''}/{db.get('NAME')}"
    return "c" + hashlib.sha256(identity.encode()).hexdigest()[:10]


def object_name(robot: str, skill: str = "", component: str = "", *, kind: str = KIND_COMPONENT) -> str:
    """Return the engine-wide unique name of one of this cloud's objects (63 characters at most)."""
    digest = hashlib.sha256(f"{cloud_id()}\0{kind}\0{robot}\0{skill}\0{component}".encode()).hexdigest()[:10]
    parts = [robot[:16], skill[:12], component[:12]] if kind == KIND_COMPONENT else [robot[:16], kind]
    readable = "-".join(_UNSAFE.sub("-", part.lower()).strip("-") for part in parts if part)
    return f"bos-{readable}-{digest}"


def labels(robot: str, skill: str = "", component: str = "", *, kind: str = KIND_COMPONENT) -> dict[str, str]:
    """Return the labels every object of this cloud carries."""
    return {
        LABEL_CLOUD: cloud_id(),
        LABEL_ROBOT: robot,
        LABEL_SKILL: skill,
        LABEL_COMPONENT: component or _SERVICE_COMPONENTS.get(kind, ""),
        LABEL_KIND: kind,
        LABEL_LOCATION: "cloud",
    }


_SERVICE_COMPONENTS = {KIND_ROS_MASTER: MASTER_COMPONENT, KIND_ROS2_DISCOVERY: DISCOVERY_COMPONENT}


def discovery_address(port: int) -> str:
    """Return "host:port" of a ROS 2 discovery server on the cloud host, as robots and cloud copies reach it."""
    return f"{settings.BRIDGEOS['CLOUD_HOST']}:{port}"


def runtime_name() -> str:
    """Return the configured cloud runtime, refusing an unknown one clearly."""
    name = settings.BRIDGEOS["CLOUD_RUNTIME"]
    if name not in RUNTIMES:
        raise ConfigError(f"BRIDGEOS_CLOUD_RUNTIME={name!r} is not a cloud runtime: use one of {', '.join(RUNTIMES)}")
    return name


def ros_networking() -> str:
    """Return how ROS nodes in the cloud are networked: 'host' or 'overlay'."""
    mode = settings.BRIDGEOS["CLOUD_ROS_NETWORK"]
    if mode not in ("host", "overlay"):
        raise ConfigError(f"BRIDGEOS_CLOUD_ROS_NETWORK={mode!r}: use 'host' or 'overlay'")
    return mode


def volumes_root() -> Path:
    """Return the directory holding every robot's cloud-side Skill volumes."""
    return Path(settings.BRIDGEOS["CLOUD_VOLUMES_DIR"])


class EngineBusy(RuntimeFailure):
    """The engine cannot do it yet (e.g. a removed robot's network still holds the subnet): try again soon."""


@dataclass(frozen=True)
class CloudSpec(ComponentSpec):
    """A component's cloud launch: the agent's spec, its launch token and the registry auth its image needs."""

    token: str = ""
    # X-Registry-Auth for the image of the cloud's registry (swarmauth.registry_auth); a secret: never printed.
    registry_auth: str = field(default="", repr=False, compare=False)


@dataclass
class Observed:
    """One object this cloud runs, as the engine reports it now."""

    robot: str
    skill: str
    component: str
    kind: str
    status: Status  # RUNNING, STARTING, EXITED (0), FAILED (crashed or refused), or ABSENT
    id: str | int | None = None
    token: str = ""
    exit_code: int | None = None
    message: str | None = None
    labels: dict[str, str] = field(default_factory=dict)

    @property
    def key(self) -> tuple[str, str, str]:
        """Return (robot, skill, component): what the desired state is keyed by."""
        return (self.robot, self.skill, self.component)


class CloudRuntime(Runtime):
    """A runtime the cloud launches components with, one instance per robot."""

    #: Whether a ROS node's peers on this host reach it over host networking.
    host_networked_ros = True

    def __init__(self, robot: str, *, data_dir: Path, **options: Any) -> None:
        super().__init__(robot, data_dir=data_dir, **options)
        self.host = settings.BRIDGEOS["CLOUD_HOST"]
        # The robot's cloud subnet (IPAM: network.ipam), for its network when it is created.
        self.subnet: str | None = None

    @abstractmethod
    async def ensure_network(self) -> str | None:
        """Create the robot's cloud network if needed and return its name (None: the runtime has none)."""

    @abstractmethod
    async def remove_network(self) -> None:
        """Remove the robot's cloud network (once nothing of the robot runs)."""

    @abstractmethod
    async def wait_running(self, skill: str, component: str, timeout: float) -> ComponentState:
        """Wait until a started copy runs; FAILED with the engine's reason if it cannot."""

    @abstractmethod
    async def endpoint(self, spec: ComponentSpec) -> dict[str, Any]:
        """Say how robots reach a running copy: runtime, id, address and published ports."""

    @abstractmethod
    async def restart(self, spec: ComponentSpec) -> ComponentState:
        """Start a crashed copy again (a fresh container, task or process)."""

    @abstractmethod
    async def start_ros_master(self, port: int) -> ComponentState:
        """Run the robot's dedicated ROS master on ``port`` of the cloud host (idempotent)."""

    @abstractmethod
    async def stop_ros_master(self) -> None:
        """Stop the robot's dedicated ROS master, if it runs."""

    @abstractmethod
    async def start_discovery_server(self, host: str, port: int) -> ComponentState:
        """Run the robot's Fast DDS discovery server on UDP ``host:port`` of the cloud host (idempotent)."""

    @abstractmethod
    async def stop_discovery_server(self) -> None:
        """Stop the robot's discovery server, if it runs."""

    @abstractmethod
    async def observe(self) -> list[Observed]:
        """List everything this cloud runs on the engine, for every robot."""

    @abstractmethod
    async def remove(self, observed: Observed) -> None:
        """Remove one object found by observe() (an orphan), whichever robot it belongs to."""

    @abstractmethod
    async def networks(self) -> dict[str, str]:
        """Map robot id to the name of every cloud network of this cloud on the engine."""

    @abstractmethod
    async def remove_network_named(self, name: str) -> None:
        """Remove one of this cloud's networks by name."""
