"""Install a new version of a running Skill beside the old one, then hand over (a Skill's `update.strategy: beside`).

balena's hand-over, per Skill: the new version's robot components start under their names while
the runtime keeps the old copies running, set aside; once every new component has run for the
Skill's `update.settle_s` with no crash or restart, the old copies stop. A new version that does
not start, or does not settle, puts the old copies back, and the Skill reports failed saying the
old version runs on. Cloud-side components are replaced: their copies stop, and start again with
the new config. A robot without the free resources for both versions, a runtime that cannot run
two copies of a component, or a new router or manager config replaces the whole Skill instead,
and says why. (A ROS 1 node that takes its old copy's name makes the ROS master shut the old one
down: the hand-over still completes; anonymous nodes publish side by side meanwhile.)
"""

from __future__ import annotations

import asyncio
from typing import TYPE_CHECKING, Any

from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import SkillStatusName as SS
from bridgeos_agent.runtime.lifecycle import SupervisedRuntime
from bridgeos_agent.skillconfig import SkillConfig

if TYPE_CHECKING:
    from bridgeos_agent.controller import RobotController
    from bridgeos_agent.state import SkillRecord

__all__ = ["hand_over", "why_not_beside"]


def why_not_beside(controller: RobotController, record: SkillRecord, config: SkillConfig) -> str | None:
    """Say why the new version cannot start beside the running one here, or None when it can."""
    if not isinstance(controller.runtime, SupervisedRuntime):
        return f"the {controller.runtime.name} runtime cannot run two copies of a component"
    old = record.config
    if (old.router, old.manager) != (config.router, config.manager):
        return "its router or manager config changes"
    staying = [name for name, where in record.locations.items() if where == "robot" and name in config.components]
    needs = {key: sum(getattr(config.components[name].resources, key) for name in staying) for key in ("cpu", "ram")}
    free = controller.monitor.free(controller.placement.reserved())
    short = [
        f"{key} {needs[key]:g} needed, {free.get(key, 0.0):g} free" for key in needs if needs[key] > free.get(key, 0)
    ]
    if short:
        return "the robot cannot run both versions at once (" + ", ".join(short) + ")"
    return None


async def hand_over(controller: RobotController, record: SkillRecord, config: SkillConfig) -> SkillRecord:
    """Start the new version beside the running one and stop the old copies once it runs (or replace)."""
    skill_id = config.skill_id
    reason = why_not_beside(controller, record, config)
    runtime = controller.runtime
    if reason is not None or not isinstance(runtime, SupervisedRuntime):
        controller.say(f"skill {skill_id}: the new version replaces the running one: {reason}")
        await controller.stop_skill(skill_id)
        return await controller.start_skill(config)
    old_config, old_locations = record.config, dict(record.locations)
    aside: dict[str, Any] = {}
    for name, where in old_locations.items():
        if where == "robot":
            copy = await runtime.set_aside(skill_id, name)
            if copy is not None:
                aside[name] = copy
                record.locations[name] = None
    await controller.placement.stop_components(record, [n for n, w in old_locations.items() if w == "cloud"])
    record.config = config
    record.locations = {name: record.locations.get(name) for name in config.components}
    await controller.set_skill_status(record, SS.STARTING)
    names = list(config.components)
    results = await asyncio.gather(
        *(controller.placement.place_component(record, name) for name in names), return_exceptions=True
    )
    failed = [f"{name}: {result}" for name, result in zip(names, results, strict=True) if isinstance(result, Exception)]
    if not failed:
        failed = await _unsettled(controller, record, config.update.settle_s)
    if failed:
        await _keep_the_old_version(controller, runtime, record, old_config, old_locations, aside)
        message = f"the new version did not start ({'; '.join(failed)}); the old version runs on"
        await controller.set_skill_status(record, SS.FAILED, message[:1900])
        return record
    for copy in aside.values():
        await runtime.stop_aside(copy)
    await controller.set_skill_status(record, SS.RUNNING)
    controller.say(f"skill {skill_id}: the new version took over from the old one, started beside it")
    controller.save_soon()
    return record


async def _unsettled(controller: RobotController, record: SkillRecord, settle_s: float) -> list[str]:
    """Watch the new version for ``settle_s``: return what of it crashed or restarted meanwhile."""
    skill_id = record.config.skill_id
    deadline = asyncio.get_running_loop().time() + settle_s
    while True:
        problems = []
        for name, where in record.locations.items():
            if where == "robot":
                state = await controller.runtime.status(skill_id, name)
                if state.status != "running" or state.restarts:
                    problems.append(f"{name}: {state.status} after {state.restarts} restart(s) {state.message or ''}")
            elif where == "cloud" and record.statuses.get(name) == CS.FAILED:
                problems.append(f"{name}: its cloud copy is {record.statuses[name]}")
        if problems or asyncio.get_running_loop().time() >= deadline:
            return [problem.strip() for problem in problems]
        await asyncio.sleep(0.1)


async def _keep_the_old_version(
    controller: RobotController,
    runtime: SupervisedRuntime[Any],
    record: SkillRecord,
    old_config: SkillConfig,
    old_locations: dict[str, str | None],
    aside: dict[str, Any],
) -> None:
    """Stop what started of the new version and put the old copies back where they ran."""
    started = [name for name, where in record.locations.items() if where is not None]
    await controller.placement.stop_components(record, started)
    record.config = old_config
    record.locations = dict.fromkeys(old_config.components)
    for name, copy in aside.items():
        await runtime.restore_aside(copy)
        record.locations[name] = "robot"
        await controller.placement.set_status(record, name, CS.RUNNING, "robot")
    for name, where in old_locations.items():
        if where == "cloud":
            try:
                await controller.placement.place_component(record, name, location="cloud")
            except Exception as exc:  # the old version's cloud copy: said, the rest still runs
                controller.say(f"skill {record.config.skill_id}/{name}: its cloud copy did not start again: {exc}")
    controller.save_soon()
