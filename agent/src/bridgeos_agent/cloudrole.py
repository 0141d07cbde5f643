"""Take over the cloud's role while it is lost, and hand it back when it returns (thesis Algorithm 7).

``takeover`` decides (``CloudMonitor``, ``plan_takeover``, ``plan_revert``); this module does
what they decide: launch the cloud components on the robot, then stop the local duplicates.
"""

from __future__ import annotations

import asyncio
import time
from typing import TYPE_CHECKING

from bridgeos_agent.allocation import allocation_state
from bridgeos_agent.heuristics import Resources
from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import ProtocolError
from bridgeos_agent.protocol import SkillStatusName as SS
from bridgeos_agent.robotconfig import RobotConfig
from bridgeos_agent.runtime import RuntimeFailure
from bridgeos_agent.takeover import CloudMonitor, plan_revert, plan_takeover

if TYPE_CHECKING:
    from bridgeos_agent.controller import RobotController

__all__ = ["CloudRole"]

# How often the takeover watch looks at the link.
WATCH_INTERVAL = 0.25


class CloudRole:
    """Watch the cloud link; run the cloud's components on the robot while the cloud is lost."""

    def __init__(self, controller: RobotController) -> None:
        self.controller = controller
        self.monitor: CloudMonitor | None = None
        self.taken: dict[str, list[str]] = {}  # skill -> components running on the robot for the cloud

    def start(self, lost_after: float) -> None:
        """Begin watching: the cloud counts as lost after ``lost_after`` s without a word."""
        self.monitor = CloudMonitor(lost_after, time.monotonic())

    def set_lost_after(self, lost_after: float) -> None:
        """Follow the robot config's ``connection_lost_after``."""
        if self.monitor is not None:
            self.monitor.disconnection_delay = lost_after

    def contact(self) -> None:
        """Note a sign of life from the cloud; hand its role back if it had been taken over."""
        if self.monitor is not None and self.monitor.on_message(time.monotonic()) == "revert":
            self.controller.spawn(self.revert())

    async def run(self) -> None:
        """Watch the link and take over once the cloud has been silent too long."""
        while True:
            await asyncio.sleep(WATCH_INTERVAL)
            # Silence counts, open socket or not: a cut link leaves the socket open until its
            # keepalive gives up (connection_lost_after later, plus the close), which would
            # double the takeover time. The session reports every frame and keepalive pong.
            if self.monitor is not None and self.monitor.tick(time.monotonic()) == "takeover":
                await self.take_over()

    def _tell_skills(self, cloud: str, event: str) -> None:
        for record in self.controller.skills.values():
            if record.supervisor is not None:
                record.supervisor.context["cloud"] = cloud
                record.supervisor.notify(event)

    async def take_over(self) -> None:
        """Run locally the cloud part of every Skill that can run whole on the robot."""
        controller = self.controller
        placement = controller.placement
        controller.say("cloud lost: taking over its role")
        self._tell_skills("lost", "connection_lost")
        running = [r.config for r in controller.skills.values() if r.status in (SS.RUNNING, SS.STARTING)]
        free = Resources(**controller.monitor.free(placement.reserved()))
        active = placement.active(running_skills_only=True)
        state = allocation_state((controller.config or RobotConfig()).resources, free, running, active)
        plan = plan_takeover(state.skills, free)
        for skill_id, names in plan.items():
            record = controller.skills[skill_id]
            started = []
            for name in names:
                try:
                    await controller.runtime.start(placement.component_spec(record, name))
                except (RuntimeFailure, ProtocolError) as exc:
                    controller.say(f"takeover: {skill_id}/{name} could not start on the robot: {exc}")
                    continue
                started.append(name)
                record.statuses[name] = CS.RUNNING
                placement.route(record, name, "robot")
            if started:
                self.taken[skill_id] = started
        count = sum(len(names) for names in self.taken.values())
        controller.say(f"takeover: {count} cloud component(s) now run on the robot")

    async def revert(self) -> None:
        """The cloud is back: hand its components back and stop the local duplicates."""
        controller = self.controller
        migrations, self.taken = self.taken, {}
        self._tell_skills("connected", "connection_established")
        stopped = 0
        for skill_id, name in plan_revert(migrations):
            record = controller.skills.get(skill_id)
            if record is not None and record.locations.get(name) == "cloud":
                controller.placement.route(record, name, "cloud")
            await controller.runtime.stop(skill_id, name)
            stopped += 1
            # Asked again: the stop took time, and the component may have moved meanwhile.
            if record is not None and record.locations.get(name) == "cloud":
                await controller.placement.set_status(record, name, CS.RUNNING, "cloud")
        controller.say(f"cloud back: {stopped} local duplicate(s) stopped")

    def components(self) -> dict[str, list[str]]:
        """Return the cloud components running on the robot because the cloud is lost."""
        return {skill: list(names) for skill, names in self.taken.items()}
