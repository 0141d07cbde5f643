"""Define the small interface every runtime implements to launch skill components."""

from __future__ import annotations

import dataclasses
import logging
import random
import re
from abc import ABC, abstractmethod
from collections import deque
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any, ClassVar

from bridgeos_agent.skillconfig import SLUG_PATTERN, VOLUME_PATTERN, ComponentResources, LaunchSpec

__all__ = [
    "ComponentSpec",
    "ComponentState",
    "RestartBudget",
    "RestartPolicy",
    "Runtime",
    "RuntimeFailure",
    "Status",
    "StatusCallback",
    "Usage",
]

logger = logging.getLogger(__name__)

# Where a component finds its skill's volumes: a mount point in a container, a
# directory under the runtime's data_dir for a process.
VOLUMES_ENV = "BRIDGEOS_VOLUMES"

_SLUG = re.compile(SLUG_PATTERN)
_VOLUME = re.compile(VOLUME_PATTERN)


class RuntimeFailure(RuntimeError):
    """Report a component that could not be launched, saying how to fix it."""


class Status(StrEnum):
    """Name where a component is in its life."""

    STARTING = "starting"
    RUNNING = "running"
    RESTARTING = "restarting"  # crashed; waiting out the backoff before the next launch
    EXITED = "exited"  # ended with exit code 0: done, not restarted
    FAILED = "failed"  # could not launch, or crashed more often than the restart policy allows
    STOPPED = "stopped"
    ABSENT = "absent"  # the runtime knows nothing of it


ACTIVE = frozenset({Status.STARTING, Status.RUNNING, Status.RESTARTING})


@dataclass(frozen=True)
class RestartPolicy:
    """Say how often a crashed component is relaunched and how long to wait each time."""

    max_restarts: int = 5
    window: float = 60.0  # seconds; restarts older than this no longer count
    backoff_initial: float = 0.5
    backoff_max: float = 30.0
    jitter: float = 0.1  # fraction of the delay added or removed at random

    def delay(self, attempt: int, rng: random.Random | None = None) -> float:
        """Return the wait before restart number ``attempt`` (0-based) within the window."""
        base = min(self.backoff_initial * 2 ** min(attempt, 62), self.backoff_max)
        if not self.jitter:
            return base
        spread = (rng or random).uniform(-self.jitter, self.jitter)
        return max(0.0, base * (1.0 + spread))


@dataclass
class RestartBudget:
    """Count a component's recent restarts to pick the next backoff or give up."""

    policy: RestartPolicy
    times: deque[float] = field(default_factory=deque)

    def next_delay(self, now: float, rng: random.Random | None = None) -> float | None:
        """Return the wait before relaunching after a crash at ``now``, or None to give up."""
        while self.times and now - self.times[0] > self.policy.window:
            self.times.popleft()
        if len(self.times) >= self.policy.max_restarts:
            return None
        delay = self.policy.delay(len(self.times), rng)
        self.times.append(now)
        return delay


@dataclass(frozen=True)
class ComponentSpec:
    """Describe one component to launch: what, where, with which env and limits."""

    robot: str
    skill: str
    component: str
    location: str
    launch: LaunchSpec
    resources: ComponentResources
    env: Mapping[str, str]
    volumes: tuple[str, ...] = ()
    restart: RestartPolicy = RestartPolicy()
    ros: bool = False  # a ROS node: it must reach the robot's ROS master and the Skill Router

    @property
    def key(self) -> tuple[str, str]:
        """Return the (skill, component) pair a runtime indexes components by."""
        return (self.skill, self.component)

    def launch_env(self) -> dict[str, str]:
        """Return the launch spec's env with the controller's contract env over it."""
        return {**self.launch.env, **self.env}

    def to_dict(self) -> dict[str, Any]:
        """Return the spec as JSON-serialisable data."""
        return {
            "robot": self.robot,
            "skill": self.skill,
            "component": self.component,
            "location": self.location,
            "launch": self.launch.model_dump(mode="json"),
            "resources": self.resources.model_dump(mode="json"),
            "env": dict(self.env),
            "volumes": list(self.volumes),
            "restart": dataclasses.asdict(self.restart),
            "ros": self.ros,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> ComponentSpec:
        """Rebuild a spec saved with to_dict."""
        return cls(
            robot=data["robot"],
            skill=data["skill"],
            component=data["component"],
            location=data["location"],
            launch=LaunchSpec.model_validate(data["launch"]),
            resources=ComponentResources.model_validate(data["resources"]),
            env=dict(data["env"]),
            volumes=tuple(data.get("volumes", ())),
            restart=RestartPolicy(**data.get("restart", {})),
            ros=bool(data.get("ros", False)),
        )


@dataclass
class ComponentState:
    """Report what a runtime knows about one component right now."""

    skill: str
    component: str
    status: Status
    pid_or_container_id: int | str | None = None
    restarts: int = 0
    exit_code: int | None = None  # 128 + N for a process killed by signal N, as Docker reports it
    started_at: float | None = None  # Unix time of the current (or last) launch
    message: str | None = None  # why it failed, for the people who must fix it

    def to_dict(self) -> dict[str, Any]:
        """Return the state as JSON-serialisable data."""
        return {**dataclasses.asdict(self), "status": str(self.status)}


@dataclass
class Usage:
    """Report what a component consumed: cores and MiB now, cumulative bytes since launch."""

    cpu: float = 0.0  # cores, averaged since the previous stats() call (or the launch)
    ram: float = 0.0  # MiB
    net_rx: int = 0
    net_tx: int = 0
    io_read: int = 0
    io_write: int = 0


StatusCallback = Callable[[ComponentState], None]


class Runtime(ABC):
    """Launch, supervise and measure a robot's skill components (JupyterHub's Spawner, per robot)."""

    name: ClassVar[str]

    def __init__(
        self,
        robot: str,
        *,
        data_dir: Path,
        on_status: StatusCallback | None = None,
        **options: Any,
    ) -> None:
        if options:
            raise TypeError(f"unknown {type(self).__name__} options: {', '.join(sorted(options))}")
        self.robot = robot
        self.data_dir = Path(data_dir)
        self.on_status = on_status
        # A component's last lines as the agent captured them (its log rings), when it captures them.
        self.ring_lines: Callable[[str, str, int], list[str]] | None = None

    def log_sources(self) -> Mapping[tuple[str, str], Any]:
        """Return where each component's output is read from (a ``logs.capture.LogSource``), by (skill, component)."""
        return {}

    @abstractmethod
    async def start(self, spec: ComponentSpec) -> ComponentState:
        """Launch a component, or return its state if it is already running."""

    @abstractmethod
    async def stop(self, skill: str, component: str, timeout: float = 10.0) -> ComponentState:
        """Stop a component: SIGTERM, then SIGKILL after ``timeout`` seconds."""

    @abstractmethod
    async def status(self, skill: str, component: str) -> ComponentState:
        """Return a component's current state (status 'absent' if unknown)."""

    @abstractmethod
    async def logs(self, skill: str, component: str, tail: int = 100) -> list[str]:
        """Return the last ``tail`` lines a component wrote to stdout and stderr."""

    @abstractmethod
    async def stats(self) -> dict[tuple[str, str], Usage]:
        """Measure every running component, keyed by (skill, component)."""

    @abstractmethod
    def get_state(self) -> dict[str, Any]:
        """Return what a restarted agent needs to re-adopt the running components."""

    @abstractmethod
    async def load_state(self, state: Mapping[str, Any]) -> list[ComponentState]:
        """Re-adopt the components of a saved state that still run; forget the rest."""

    @abstractmethod
    async def close(self, stop_components: bool = False) -> None:
        """Release the runtime; components keep running unless ``stop_components``."""

    def _notify(self, state: ComponentState) -> None:
        """Tell the owner about a status change without letting its errors reach us."""
        if self.on_status is None:
            return
        try:
            self.on_status(dataclasses.replace(state))
        except Exception:
            logger.exception("on_status callback failed for %s/%s", state.skill, state.component)


def absent(skill: str, component: str) -> ComponentState:
    """Return the state of a component a runtime does not know."""
    return ComponentState(skill=skill, component=component, status=Status.ABSENT)


def check_ids(skill: str, component: str, volumes: tuple[str, ...] = ()) -> None:
    """Refuse ids that are not slugs: they become paths, container names and ROS namespaces."""
    for what, value in (("skill", skill), ("component", component)):
        if not _SLUG.fullmatch(value):
            raise ValueError(f"invalid {what} id {value!r}: expected a slug matching {SLUG_PATTERN}")
    for volume in volumes:
        if not _VOLUME.fullmatch(volume):
            raise ValueError(f"invalid volume name {volume!r}: expected a Docker volume name matching {VOLUME_PATTERN}")


def unrunnable(code: int | None, who: str, command: object = None) -> str | None:
    """Explain an exit code saying the command itself could not run, which no restart fixes."""
    reason = {126: "is not executable", 127: "was not found"}.get(code or 0)
    if reason is None:
        return None
    named = f" {command!r}" if command else ""
    return f"{who}: its command{named} {reason} (exit {code}): fix the command in the skill's robot launch spec"


def give_up_message(who: str, policy: RestartPolicy, code: int | None) -> str:
    """Explain why a crashing component is no longer restarted."""
    return (
        f"{who} crashed {policy.max_restarts + 1} times within {policy.window:.0f} s "
        f"(last exit code {code}); not restarted again: see its logs"
    )


def exit_code(returncode: int) -> int:
    """Map a Popen return code to a shell-style exit code (signal N → 128 + N)."""
    return 128 - returncode if returncode < 0 else returncode
