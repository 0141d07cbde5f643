"""The narrow view of the Robot Controller that a Skill's manager, router and volume sync use."""

from __future__ import annotations

import asyncio
from collections.abc import Coroutine, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

from bridgeos_agent.protocol import Envelope, Event

if TYPE_CHECKING:
    from bridgeos_agent.agentsettings import AgentSettings
    from bridgeos_agent.metrics import AgentMetrics
    from bridgeos_agent.monitor import ResourceMonitor
    from bridgeos_agent.robotconfig import RobotConfig
    from bridgeos_agent.runtime import Runtime, Usage
    from bridgeos_agent.state import SkillRecord

__all__ = ["SkillHost"]


class SkillHost(Protocol):
    """What the robot offers the per-Skill parts it runs (the Robot Controller implements it)."""

    @property
    def settings(self) -> AgentSettings:
        """Return what the agent was told at start (robot id, intervals)."""
        ...

    @property
    def data_dir(self) -> Path:
        """Return the agent's data directory."""
        ...

    @property
    def skills(self) -> Mapping[str, SkillRecord]:
        """Return the robot's Skills by id."""
        ...

    @property
    def config(self) -> RobotConfig | None:
        """Return the robot config in force (None before the first)."""
        ...

    @property
    def ros_master(self) -> str | None:
        """Return the ROS master components use."""
        ...

    @property
    def monitor(self) -> ResourceMonitor:
        """Return the robot's resource monitor."""
        ...

    @property
    def runtime(self) -> Runtime:
        """Return the runtime that runs the robot's components."""
        ...

    @property
    def usage(self) -> Mapping[tuple[str, str], Usage]:
        """Return the runtime's last measurement of each robot-side component, by (skill, component)."""
        ...

    @property
    def connected(self) -> asyncio.Event:
        """Return the event set while the cloud link is up."""
        ...

    @property
    def metrics(self) -> AgentMetrics:
        """Return the counters the agent's --metrics serves."""
        ...

    def say(self, line: str) -> None:
        """Tell the robot's owner something."""
        ...

    def link_latency(self) -> float:
        """Return the cloud link's round trip in seconds (0 when unknown)."""
        ...

    def spawn(self, coroutine: Coroutine[Any, Any, Any]) -> None:
        """Run a coroutine in the background, owned by the controller."""
        ...

    async def emit(self, event: Event, data: Mapping[str, Any], *, reply_to: str | None = None) -> Envelope:
        """Send a frame to the cloud."""
        ...

    async def request(self, event: Event, data: Mapping[str, Any], timeout: float = 10.0) -> Envelope | None:
        """Ask the cloud something and wait for the answer."""
        ...

    async def migrate_component(self, record: SkillRecord, name: str, target: str | None) -> str:
        """Move a running component to the other side."""
        ...
