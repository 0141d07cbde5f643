"""Releases a Skill installs beside its running version (`update.strategy: beside`), with real agents.

Each component notes in the Skill's volume when it starts and when it is told to stop, so the
order of the two versions' lives shows how the robot installed the release: beside (the new
version started before the old one stopped), or replacing it (the old stopped first).
"""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.controller import RobotController
from bridgeos_agent.protocol import SkillStatusName
from bridgeos_agent.skillconfig import parse_skill_config
from monitoring.models import Event as LogEvent
from rollouts.models import RolloutRobot
from tests.rollouts.test_rollout_agents import (
    SKILL,
    agents,
    old_version_running,
    release,
    running_everywhere,
    start_rollout,
    tick_until,
)

pytestmark = pytest.mark.django_db(transaction=True)

# Notes "VERSION start NS" (its stop trap set by then) and, told to stop, "VERSION stop NS"; serves in between.
NOTING = (
    'f="$BRIDGEOS_VOLUMES/data/lives.log"; trap \'echo "VERSION stop $(date +%s%N)" >> "$f"; exit 0\' TERM; '
    'echo "VERSION start $(date +%s%N)" >> "$f"; while true; do sleep 0.05; done'
)


def noting(version: str, *, ram: float = 16, command: list[str] | None = None) -> dict[str, Any]:
    """A one-component Skill that installs its new versions beside the running one."""
    robot = {"command": command or ["sh", "-c", NOTING.replace("VERSION", version)]}
    component = {"name": "detect", "location": "robot", "ros": False, "resources": {"cpu": 0.1, "ram": ram}}
    config = {
        "skill": f"Detector {version}",
        "skill_id": SKILL,
        "volumes": ["data"],
        "update": {"strategy": "beside"},
        "components": {"detect": {**component, "robot": robot}},
    }
    return parse_skill_config(config).model_dump(mode="json")


def lives(controller: RobotController) -> dict[tuple[str, str], int]:
    """When each version started and stopped on this robot: {(version, "start"|"stop"): ns}."""
    path = controller.runtime.volumes_dir(SKILL) / "data" / "lives.log"
    found: dict[tuple[str, str], int] = {}
    for line in path.read_text().splitlines() if path.exists() else []:
        version, event, ns = line.split()
        found.setdefault((version, event), int(ns))
    return found


@sync_to_async
def fleet_of(count: int, config: dict[str, Any]) -> tuple[Any, list[tuple[str, str]]]:
    from django.contrib.auth import get_user_model

    from robots.services import create_robot
    from skills.services import add_skill

    owner = get_user_model().objects.create_user("beside-owner")
    robots = []
    for n in range(count):
        robot, token = create_robot(f"beside-{n}", owner, labels={"site": "lab"})
        add_skill(robot, config)
        robots.append((robot.id, token))
    return owner, robots


async def old_version_reported(robots: list[tuple[str, str]], controllers: list[RobotController]) -> None:
    """Wait until every old version noted its start and the cloud heard it run (a rollout reads that to choose)."""
    from skills.models import Skill

    for _ in range(100):
        if all(("v1", "start") in lives(c) for c in controllers):
            break
        await asyncio.sleep(0.05)

    ids = [robot_id for robot_id, _ in robots]
    for _ in range(100):
        statuses = await sync_to_async(set)(Skill.objects.filter(robot_id__in=ids).values_list("status", flat=True))
        if statuses == {"running"}:
            return
        await asyncio.sleep(0.1)
    pytest.fail(f"the cloud did not hear the old version run: {statuses}")


async def stopped_noted(controllers: list[RobotController], version: str) -> None:
    for _ in range(50):
        if all((version, "stop") in lives(c) for c in controllers):
            return
        await asyncio.sleep(0.1)
    pytest.fail(f"{version} did not note its stop on every robot: {[lives(c) for c in controllers]}")


async def test_a_release_starts_beside_the_running_version_and_the_old_one_stops_once_it_runs(
    cloud, tmp_path: Path
) -> None:
    owner, robots = await fleet_of(3, noting("v1"))
    made = await release(owner, noting("v2"))
    async with agents(cloud, robots, tmp_path) as controllers:
        await old_version_running(robots)
        await running_everywhere(controllers, "v1")
        await old_version_reported(robots, controllers)
        rollout = await start_rollout(owner, made, "site=lab", strategy={"first": 1, "soak_s": 1, "pause_s": 0})
        done = await tick_until(rollout.id, {"succeeded", "rolled_back", "paused"}, timeout=90)
        assert done.state == "succeeded", done.reason
        await running_everywhere(controllers, "v2", timeout=5)
        await stopped_noted(controllers, "v1")
        for controller in controllers:
            life = lives(controller)
            # Beside: the new version ran before the old one was told to stop.
            assert life[("v2", "start")] < life[("v1", "stop")], life
            assert ("v2", "stop") not in life
    members = await sync_to_async(list)(RolloutRobot.objects.filter(rollout=rollout))
    assert {m.status for m in members} == {"succeeded"}


async def test_a_robot_without_room_for_both_versions_replaces_the_running_one(cloud, tmp_path: Path, caplog) -> None:
    # 1,200 MiB each on a simulated robot of 2,048: one version fits, two do not.
    owner, robots = await fleet_of(1, noting("v1", ram=1200))
    made = await release(owner, noting("v2", ram=1200))
    async with agents(cloud, robots, tmp_path) as controllers:
        await old_version_running(robots)
        await running_everywhere(controllers, "v1")
        await old_version_reported(robots, controllers)
        rollout = await start_rollout(owner, made, "site=lab", strategy={"first": 1, "soak_s": 1})
        done = await tick_until(rollout.id, {"succeeded", "rolled_back", "paused"}, timeout=90)
        assert done.state == "succeeded", done.reason
        await running_everywhere(controllers, "v2", timeout=5)
        life = lives(controllers[0])
        assert life.get(("v1", "stop"), float("inf")) < life.get(("v2", "start"), 0), life
    assert "the new version replaces the running one: the robot cannot run both versions at once (ram" in caplog.text


async def test_a_new_version_that_does_not_start_leaves_the_old_copies_running(cloud, tmp_path: Path) -> None:
    _, robots = await fleet_of(1, noting("v1"))
    async with agents(cloud, robots, tmp_path) as controllers:
        await old_version_running(robots)
        await running_everywhere(controllers, "v1")
        controller = controllers[0]
        before = await controller.runtime.status(SKILL, "detect")
        broken = parse_skill_config(noting("v2", command=["/nonexistent/detector"]))
        record = await controller.start_skill(broken)
        assert record.status == SkillStatusName.FAILED
        after = await controller.runtime.status(SKILL, "detect")
        # The very copy that ran before, still supervised under its name, and the old config in force.
        assert (after.status, after.pid_or_container_id) == ("running", before.pid_or_container_id)
        assert record.config.skill == "Detector v1" and record.locations == {"detect": "robot"}
        await asyncio.sleep(0.3)
        assert ("v1", "stop") not in lives(controller)
        # The cloud hears why, and that the old version runs on (its event log).
        said = ""
        for _ in range(50):
            said = "\n".join(await sync_to_async(list)(LogEvent.objects.values_list("message", flat=True)))
            if "the old version runs on" in said:
                break
            await asyncio.sleep(0.1)
        assert "did not start (detect:" in said and "the old version runs on" in said, said
