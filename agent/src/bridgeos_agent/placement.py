"""Place a Skill's components: Algorithm 1 against the robot's state, start/stop/migrate, and Replace.

A component goes where its config, the offloading mode or its last placement says; on the
robot only if Algorithm 1 finds room (else the cloud, or a cheaper component is replaced
to the cloud first). A migration starts the new copy, switches the router, then stops the
old one, so there is no window without a serving copy.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from bridgeos_agent.allocation import (
    ActiveLocation,
    AllocationDecision,
    AllocationSettings,
    Cloud,
    Measurement,
    Refuse,
    Replace,
    allocate,
    allocation_state,
)
from bridgeos_agent.heuristics import Resources, Weights
from bridgeos_agent.monitor import RESOURCES
from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import Envelope, Event, ProtocolError
from bridgeos_agent.protocol import SkillStatusName as SS
from bridgeos_agent.robotconfig import RobotConfig
from bridgeos_agent.ros2graph import Ros2Graph, namespace_arguments
from bridgeos_agent.rosnames import instance_namespace
from bridgeos_agent.runtime import ComponentSpec, ComponentState, RuntimeFailure, Status
from bridgeos_agent.state import SkillRecord, previous_placement

if TYPE_CHECKING:
    from bridgeos_agent.controller import RobotController

__all__ = ["Placement", "check_location", "migration_target"]

PULL_REPORT_S = 1.0  # how often a pull's progress goes to the cloud


def check_location(name: str, required: str, location: str) -> None:
    """Refuse to start a component where its Skill config does not let it run."""
    if location == "cloud":
        if required == "robot":
            raise ProtocolError(f"component {name!r} may only run on the robot", field="data.location")
    elif required == "cloud":
        raise ProtocolError(f"component {name!r} may only run in the cloud", field="data.location")


def migration_target(name: str, required: str, current: str | None, target: str | None) -> str:
    """Return where a migration goes (``target``, else the other side); refuse a component that may not move."""
    if required != "either":
        raise ProtocolError(f"component {name!r} may only run on the {required}", field="data.component")
    return target or ("robot" if current == "cloud" else "cloud")


class Placement:
    """Decide where each component runs, start it there, and move or stop it on request."""

    def __init__(self, controller: RobotController) -> None:
        self.controller = controller
        self._lock = asyncio.Lock()  # serialises placement decisions so two never claim the same headroom
        self._cloud_waiters: dict[tuple[str, str], asyncio.Future[tuple[str, str | None]]] = {}
        # Each component's latest runtime report being sent: the next waits for it, so a crash report
        # (slower: it reads the last lines first) never reaches the cloud after the relaunch's.
        self._reports: dict[tuple[str, str], asyncio.Task[None]] = {}

    # ------------------------------------------------------------------ Algorithm 1

    def allocation_settings(self) -> AllocationSettings:
        """Return Algorithm 1's settings from the robot config."""
        config = self.controller.config or RobotConfig()
        weights = Weights(**config.weights.model_dump())
        return AllocationSettings(
            heuristic=config.heuristic, threshold=config.threshold, weights=weights, per_gb=config.costs.per_gb
        )

    def allocate(self, skill_id: str, component_id: str) -> AllocationDecision:
        """Run Algorithm 1 for one component against the robot's state now."""
        controller = self.controller
        total = (controller.config or RobotConfig()).resources
        free = controller.monitor.free(self.reserved())
        measurements = {
            key: Measurement(usage=Resources(cpu=usage.cpu, ram=usage.ram)) for key, usage in controller.usage.items()
        }
        configs = [record.config for record in controller.skills.values()]
        state = allocation_state(total, Resources(**free), configs, self.active(), measurements)
        return allocate(state, skill_id, component_id, self.allocation_settings())

    def active(self, *, running_skills_only: bool = False) -> dict[tuple[str, str], ActiveLocation]:
        """Map each (skill, component) that runs somewhere to where it runs."""
        return {
            (skill, name): "cloud" if where == "cloud" else "robot"
            for skill, record in self.controller.skills.items()
            if not running_skills_only or record.status in (SS.RUNNING, SS.STARTING)
            for name, where in record.locations.items()
            if where is not None
        }

    def reserved(self) -> dict[str, float]:
        """Sum the declared needs of every component running on the robot."""
        used = dict.fromkeys(RESOURCES, 0.0)
        for record in self.controller.skills.values():
            for name, where in record.locations.items():
                if where == "robot":
                    needs = record.config.components[name].resources
                    for key in used:
                        used[key] += getattr(needs, key)
        return used

    def _preferred_location(self, required: str, skill_id: str, name: str) -> str:
        if required in ("robot", "cloud"):
            return required
        config = self.controller.config
        mode = config.offloading if config else "auto"
        if mode == "auto":
            # Previous launches are the backbone of the first placement (thesis §3.4.1):
            # start where the manager last settled the component.
            return previous_placement(self.controller.data_dir, skill_id).get(name, "robot")
        return "cloud" if mode == "cloud" else "robot"

    # ------------------------------------------------------------------ start

    async def place_component(self, record: SkillRecord, name: str, *, location: str | None = None) -> str:
        """Start a component where it should run; return that location."""
        component = record.config.components[name]
        target = location or self._preferred_location(component.location, record.config.skill_id, name)
        check_location(name, component.location, target)
        if target == "cloud":
            await self.start_in_cloud(record, name)
            return "cloud"
        async with self._lock:
            decision = self.allocate(record.config.skill_id, name)
            if isinstance(decision, Replace):
                replaced = self.controller.skills[decision.skill_id]
                self.controller.say(
                    f"{record.config.skill_id}/{name}: moving {decision.skill_id}/{decision.component_id} "
                    f"to the cloud first ({decision.reason})"
                )
                for moved in (decision.component_id, *decision.links):
                    # A migration: the robot copy serves until its cloud copy runs and the router
                    # switches; if the cloud cannot run it, it stays and this placement fails saying why.
                    await self.migrate_component(replaced, moved, "cloud")
            elif isinstance(decision, Cloud):
                if location == "robot":
                    raise ProtocolError(f"no room on the robot for {name!r}: {decision.reason}", code="no_resources")
                await self.start_in_cloud(record, name)
                return "cloud"
            elif isinstance(decision, Refuse):
                await self.set_status(record, name, CS.FAILED, None, decision.reason)
                raise ProtocolError(f"no room on the robot for {name!r}: {decision.reason}", code="no_resources")
            await self._start_on_robot(record, name)
        return "robot"

    def component_spec(self, record: SkillRecord, name: str) -> ComponentSpec:
        """Build the launch spec of a robot-side component with the env contract."""
        controller = self.controller
        component = record.config.components[name]
        launch = component.robot
        if launch is None:
            raise ProtocolError(f"component {name!r} has no robot launch spec", field=f"components.{name}.robot")
        env = {
            "BRIDGEOS_ROBOT": controller.settings.robot,
            "BRIDGEOS_SKILL": record.config.skill_id,
            "BRIDGEOS_COMPONENT": name,
            "BRIDGEOS_LOCATION": "robot",
        }
        if controller.ros_master:
            env["ROS_MASTER_URI"] = controller.ros_master
        if component.ros_version:
            # The Skill Router relays between this namespace and the names peers use.
            env["ROS_NAMESPACE"] = namespace = instance_namespace(record.config.skill_id, name, "robot")
            if component.ros_version == 2:
                # ROS 2 reads its namespace from the command line, not from ROS_NAMESPACE.
                env.update((controller.ros2_graph or Ros2Graph()).env())
                env["BRIDGEOS_ROS_ARGS"] = " ".join(namespace_arguments(namespace))
                if launch.command:
                    launch = launch.model_copy(update={"command": [*launch.command, *namespace_arguments(namespace)]})
        plugin_env = record.context("env")
        if isinstance(plugin_env, dict):
            env.update({k: str(v) for k, v in plugin_env.items()})
        return ComponentSpec(
            robot=controller.settings.robot,
            skill=record.config.skill_id,
            component=name,
            location="robot",
            launch=launch,
            resources=component.resources,
            env=env,
            volumes=tuple(record.config.volumes),
            ros=bool(component.ros_version),
        )

    async def _start_on_robot(self, record: SkillRecord, name: str) -> None:
        controller = self.controller
        spec = self.component_spec(record, name)
        await self.set_status(record, name, CS.STARTING, "robot")
        try:
            state = await controller.runtime.start(spec)
        except RuntimeFailure as exc:
            await self.set_status(record, name, CS.FAILED, "robot", str(exc))
            raise ProtocolError(str(exc), code="launch_failed") from None
        record.locations[name] = "robot"
        self._route_first(record, name, "robot")
        await self.set_status(record, name, CS.RUNNING, "robot")
        await controller.emit(
            Event.COMPONENT_LOCATION, {"skill": record.config.skill_id, "component": name, "location": "robot"}
        )
        container: dict[str, Any] = {"runtime": controller.runtime.name}
        launch = record.config.components[name].robot
        if controller.runtime.name == "docker" and launch is not None and launch.image:
            container["image"] = launch.image[:256]  # pinned by the cloud: the digest it runs shows
        ident = state.pid_or_container_id
        if isinstance(ident, int):
            container["pid"] = ident
        elif ident:
            container["id"] = str(ident)[:64]
        await controller.emit(
            Event.COMPONENT_INFORMATION,
            {"skill": record.config.skill_id, "component": name, "location": "robot", "container": container},
        )
        controller.save_soon()

    async def start_in_cloud(self, record: SkillRecord, name: str, *, wait: float | None = None) -> None:
        """Forward a cloud-side launch to the cloud; with ``wait``, return once it runs there, raise if not."""
        controller = self.controller
        data = {"skill": record.config.skill_id, "component": name, "location": "cloud"}
        # The Skill's volumes as they are now go ahead of the start: the cloud starts the copy once written.
        await controller.volumes.flush(record.config.skill_id)
        if wait is None:
            record.locations[name] = "cloud"
            self._route_first(record, name, "cloud")
            await self.set_status(record, name, CS.STARTING, "cloud")
            await controller.emit(Event.COMPONENT_START, data)
            controller.save_soon()
            return
        key = (record.config.skill_id, name)
        reported = self._cloud_waiters[key] = asyncio.get_running_loop().create_future()
        try:
            await controller.emit(Event.COMPONENT_START, data)
            status, message = await asyncio.wait_for(asyncio.shield(reported), wait)
        except TimeoutError:
            await controller.emit(Event.COMPONENT_STOP, data)  # a copy that comes up later must not linger
            raise ProtocolError(f"the cloud did not run {name!r} within {wait:g} s", code="cloud_timeout") from None
        finally:
            if self._cloud_waiters.get(key) is reported:
                del self._cloud_waiters[key]
        if status != CS.RUNNING:
            raise ProtocolError(f"the cloud could not run {name!r}: {message or status}", code="launch_failed")
        record.locations[name] = "cloud"
        self._route_first(record, name, "cloud")
        controller.save_soon()

    def on_cloud_report(self, skill_id: str, name: str, status: str, message: str | None) -> None:
        """Take in what the cloud says of a component's cloud copy (running, restarting, failed)."""
        waiter = self._cloud_waiters.get((skill_id, name))
        if waiter is not None:
            if not waiter.done() and status in (CS.RUNNING, CS.FAILED):
                waiter.set_result((status, message))
            return
        record = self.controller.skills.get(skill_id)
        if record is None or record.locations.get(name) != "cloud":
            return  # a copy being retired, or a move still deciding: nothing changes here
        record.statuses[name] = CS(status)
        if status == CS.FAILED:
            record.locations[name] = None
            self.controller.say(f"{skill_id}/{name}: its cloud copy failed: {message or 'no reason given'}")
            self.controller.save_soon()

    def on_refused(self, frame: Envelope, message: str) -> None:
        """A cloud launch the cloud refused for good: the component runs nowhere, and says why."""
        if frame.event != Event.COMPONENT_START:
            return
        data = frame.data
        record = self.controller.skills.get(data["skill"])
        if record is not None and record.locations.get(data["component"]) == "cloud":
            record.locations[data["component"]] = None
            self.controller.spawn(self.set_status(record, data["component"], CS.FAILED, None, message))

    # ------------------------------------------------------------------ stop and move

    async def stop_component(self, record: SkillRecord, name: str, *, only: str | None = None) -> None:
        """Stop a component where it runs (or only at ``only``)."""
        controller = self.controller
        where = record.locations.get(name)
        skill_id = record.config.skill_id
        if where == "robot" and only in (None, "robot"):
            await self.set_status(record, name, CS.STOPPING, "robot")
            await controller.runtime.stop(skill_id, name)
        elif where == "cloud" and only in (None, "cloud"):
            await controller.emit(Event.COMPONENT_STOP, {"skill": skill_id, "component": name, "location": "cloud"})
        if only is None or only == where:
            record.locations[name] = None
            self.route(record, name, None)
            await self.set_status(record, name, CS.STOPPED, None)
        controller.forget_component(skill_id, name)
        controller.save_soon()

    async def stop_components(self, record: SkillRecord, names: list[str]) -> None:
        """Stop several components of a Skill at once; one that fails to stop does not stop the others."""
        await asyncio.gather(*(self.stop_component(record, name) for name in names), return_exceptions=True)

    async def migrate_component(self, record: SkillRecord, name: str, target: str | None) -> str:
        """Move a running component to the other side: start there first, then stop here."""
        controller = self.controller
        component = record.config.components[name]
        current = record.locations.get(name)
        target = migration_target(name, component.location, current, target)
        if target == current:
            return target
        await self.set_status(record, name, CS.MIGRATING, current)
        # The old copy keeps serving until the new one runs and the router switches (no downtime window).
        try:
            if target == "robot":
                await self.place_component(record, name, location="robot")
            else:
                # Nothing switches before the cloud reports its copy running.
                await self.start_in_cloud(record, name, wait=controller.settings.cloud_start_timeout)
        except Exception as exc:
            # Rolled back: the component keeps running where it was, and the cloud hears why (re-raised).
            controller.metrics.migrated(record.config.skill_id, "failed")
            record.locations[name] = current
            await self.set_status(record, name, CS.RUNNING if current else CS.STOPPED, current, f"not moved: {exc}")
            raise
        router = record.context("router")
        if router is not None and current is not None:
            if not await router.wait_ready(name, target, router.settings.ready_timeout):
                controller.metrics.migrated(record.config.skill_id, "abandoned")
                await self._abandon_migration(record, name, target, current)
                raise ProtocolError(
                    f"component {name!r} was not ready on the {target} within {router.settings.ready_timeout:g} s; "
                    f"it keeps running on the {current}",
                    field="data.component",
                    code="migration_failed",
                )
            await router.switch(name, target)
        elif router is not None:
            router.set_active(name, target)
        if current == "cloud":
            await controller.emit(
                Event.COMPONENT_STOP, {"skill": record.config.skill_id, "component": name, "location": "cloud"}
            )
        elif current == "robot":
            await controller.runtime.stop(record.config.skill_id, name)
            controller.usage.pop((record.config.skill_id, name), None)
        await controller.emit(
            Event.COMPONENT_LOCATION, {"skill": record.config.skill_id, "component": name, "location": target}
        )
        if target == "cloud":
            await self.set_status(record, name, CS.RUNNING, "cloud")
        controller.metrics.migrated(record.config.skill_id, "done")
        return target

    async def _abandon_migration(self, record: SkillRecord, name: str, target: str, current: str) -> None:
        """Stop the copy that did not get ready and keep the old one in charge."""
        controller = self.controller
        skill_id = record.config.skill_id
        if target == "robot":
            await controller.runtime.stop(skill_id, name)
        else:
            await controller.emit(Event.COMPONENT_STOP, {"skill": skill_id, "component": name, "location": "cloud"})
        record.locations[name] = current
        await self.set_status(record, name, CS.RUNNING, current, f"migration to the {target} abandoned: not ready")
        await controller.emit(Event.COMPONENT_LOCATION, {"skill": skill_id, "component": name, "location": current})
        controller.save_soon()

    # ------------------------------------------------------------------ routing and statuses

    def route(self, record: SkillRecord, name: str, location: str | None) -> None:
        """Point the Skill's router at one instance of a component (or at none)."""
        router = record.context("router")
        if router is not None:
            # A router that does not route this component refuses it; nothing to point then.
            with contextlib.suppress(ValueError):
                router.set_active(name, location)

    def _route_first(self, record: SkillRecord, name: str, location: str) -> None:
        """Let the router follow a component's first start (a migration switches it instead)."""
        router = record.context("router")
        if router is not None and router.active(name) is None:
            self.route(record, name, location)

    def pull_progress(self, skill: str, component: str, image: str) -> Callable[[int, int], None]:
        """Return what reports a pull of a component's image: to the cloud at most once a second and at its end."""
        controller = self.controller
        told = {"at": 0.0}
        counted = {"bytes": 0}  # the bytes done when the cloud was last told

        def report(done: int, total: int) -> None:
            now = time.monotonic()
            if done < total and now - told["at"] < PULL_REPORT_S:
                return
            controller.metrics.image_pulled(skill, component, max(0, done - counted["bytes"]))
            told["at"], counted["bytes"] = now, done
            pull = {"image": image[:256], "done": done, "total": total}
            container = {"runtime": controller.runtime.name, "image": image[:256], "pull": pull}
            data = {"skill": skill, "component": component, "location": "robot", "container": container}
            controller.spawn(controller.emit(Event.COMPONENT_INFORMATION, data))

        return report

    async def set_status(
        self,
        record: SkillRecord,
        name: str,
        status: CS,
        location: str | None,
        message: str | None = None,
        *,
        crashed: bool = False,
    ) -> None:
        """Record a component's status and report it to the cloud (a crash's with the last lines it printed)."""
        record.statuses[name] = status
        data: dict[str, Any] = {"skill": record.config.skill_id, "component": name, "status": str(status)}
        if location:
            data["location"] = location
        if message:
            data["message"] = message[:1900]
        if crashed:
            data["last_lines"] = await self.controller.logs.last_lines(record.config.skill_id, name)
        await self.controller.emit(Event.COMPONENT_STATUS, data)

    def on_runtime_status(self, state: ComponentState) -> None:
        """Report a component's crash, restart or give-up that the runtime saw."""
        record = self.controller.skills.get(state.skill)
        if record is None or state.component not in record.config.components:
            return
        if state.status == Status.RESTARTING:
            self.controller.metrics.component_restarted(state.skill, state.component)
        mapped = {
            Status.RUNNING: CS.RUNNING,
            Status.STARTING: CS.STARTING,
            Status.RESTARTING: CS.STARTING,
            Status.FAILED: CS.FAILED,
            Status.EXITED: CS.STOPPED,
        }.get(state.status)
        if mapped is None or record.locations.get(state.component) != "robot":
            return
        if record.statuses.get(state.component) == mapped:
            return
        message = None
        if state.status == Status.RESTARTING:
            message = f"crashed (exit code {state.exit_code}); restart {state.restarts}"
            if state.message:
                message += f": {state.message}"  # what the runtime knows more, e.g. killed over its memory limit
        elif state.status == Status.FAILED:
            message = f"crashed too often (exit code {state.exit_code}); gave up"
        crashed = state.status in (Status.RESTARTING, Status.FAILED) and state.exit_code not in (None, 0)
        record.statuses[state.component] = mapped
        key = (state.skill, state.component)
        report = self._report(self._reports.get(key), record, state.component, mapped, message, crashed)
        task = self._reports[key] = self.controller.tasks.spawn(report)
        task.add_done_callback(lambda done: self._reports.pop(key) if self._reports.get(key) is done else None)

    async def _report(
        self,
        previous: asyncio.Task[None] | None,
        record: SkillRecord,
        name: str,
        status: CS,
        message: str | None,
        crashed: bool,
    ) -> None:
        """Send a runtime report once the component's previous one went."""
        if previous is not None:
            await asyncio.wait([previous])
        await self.set_status(record, name, status, "robot", message, crashed=crashed)
