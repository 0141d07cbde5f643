"""Rollouts against the real cloud (daphne, Celery, PostgreSQL, Redis) and real agents in simulate mode.

The executor's steps are taken by the test's own ticks (the Celery beat's task, called in
this process) as well as by the worker the creation kicks; the robots are real Robot
Controllers running their Skills' components as processes.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.controller import RobotController
from bridgeos_agent.protocol import SkillStatusName
from bridgeos_agent.skillconfig import parse_skill_config
from robots.services import create_robot
from rollouts import executor
from rollouts.models import Rollout, RolloutRobot
from tests.agent.conftest import Cloud, agent_settings, configured

pytestmark = pytest.mark.django_db(transaction=True)

SKILL = "detector"


def detector(version: str, *, crash_after_s: float | None = None) -> dict[str, Any]:
    """A Skill of two process components whose command line names the version (a crash: exits after a while)."""
    run = f"exec sleep 600 # {version}" if crash_after_s is None else f"sleep {crash_after_s}; exit 3 # {version}"
    spec = {"command": ["sh", "-c", run]}
    components = {
        name: {"name": name, "location": "robot", "ros": False, "resources": {"cpu": 0.1, "ram": 16}, "robot": spec}
        for name in ("camera", "detect")
    }
    config = {"skill": f"Detector {version}", "skill_id": SKILL, "components": components}
    return parse_skill_config(config).model_dump(mode="json")


@sync_to_async
def fleet(count: int, labels: dict[str, str]) -> tuple[Any, list[tuple[str, str]]]:
    """One owner's robots with the old version added: (owner, [(robot id, token)])."""
    from django.contrib.auth import get_user_model

    from skills.services import add_skill

    owner = get_user_model().objects.create_user("fleet-owner")
    robots = []
    for n in range(count):
        robot, token = create_robot(f"bot-{n:02d}", owner, labels=labels)
        add_skill(robot, detector("v1"))
        robots.append((robot.id, token))
    return owner, robots


@sync_to_async
def release(owner: Any, config: dict[str, Any]) -> Any:
    from rollouts.services import create_release
    from teams.services import personal_organization

    return create_release(personal_organization(owner), config, user=owner)


@sync_to_async
def start_rollout(owner: Any, made: Any, selector: str, **kw: Any) -> Rollout:
    from rollouts.rolling import create_rollout

    return create_rollout(made, selector, user=owner, **kw)


@contextlib.asynccontextmanager
async def agents(cloud: Cloud, robots: list[tuple[str, str]], tmp: Path) -> AsyncIterator[list[RobotController]]:
    """Run every robot's agent, each started with its Skill running (the old version)."""
    controllers = [
        RobotController(agent_settings(cloud, robot_id, token, tmp / robot_id)) for robot_id, token in robots
    ]
    async with contextlib.AsyncExitStack() as stack:
        for controller in controllers:
            await stack.enter_async_context(configured(controller))
        yield controllers


def versions(controllers: list[RobotController]) -> dict[str, str]:
    """What each robot runs now: the version its running Skill's config names (or its status)."""
    found = {}
    for controller in controllers:
        record = controller.skills.get(SKILL)
        if record is None:
            found[controller.settings.robot] = "none"
        elif record.status != SkillStatusName.RUNNING:
            found[controller.settings.robot] = str(record.status)
        else:
            found[controller.settings.robot] = record.config.skill.split()[-1]
    return found


async def tick_until(rollout_id: int, states: set[str], timeout: float) -> Rollout:
    """Take executor steps until the rollout reaches one of ``states``; return it."""
    deadline = time.monotonic() + timeout
    while True:
        await sync_to_async(executor.tick)()
        rollout = await sync_to_async(Rollout.objects.get)(pk=rollout_id)
        if rollout.state in states:
            return rollout
        if time.monotonic() > deadline:
            members = await sync_to_async(list)(RolloutRobot.objects.filter(rollout_id=rollout_id).values())
            pytest.fail(f"rollout {rollout_id} is {rollout.state} ({rollout.reason}) after {timeout} s: {members}")
        await asyncio.sleep(0.2)


@sync_to_async
def old_version_running(robots: list[tuple[str, str]]) -> None:
    from robots.services import push_to_robot
    from skills.models import Skill
    from skills.services import start_order

    for robot_id, _ in robots:
        push_to_robot(robot_id, "skill_start", start_order(Skill.objects.get(robot_id=robot_id, skill_id=SKILL)))


async def running_everywhere(controllers: list[RobotController], version: str, timeout: float = 30) -> None:
    deadline = time.monotonic() + timeout
    while set(versions(controllers).values()) != {version}:
        if time.monotonic() > deadline:
            pytest.fail(f"not all robots run {version}: {versions(controllers)}")
        await asyncio.sleep(0.1)


async def test_a_good_release_reaches_every_robot_batch_after_batch(cloud, tmp_path) -> None:
    owner, robots = await fleet(6, {"site": "lab"})
    made = await release(owner, detector("v2"))
    async with agents(cloud, robots, tmp_path) as controllers:
        await old_version_running(robots)
        await running_everywhere(controllers, "v1")
        rollout = await start_rollout(
            owner, made, "site=lab", strategy={"first": 1, "factor": 2, "soak_s": 1, "pause_s": 0}
        )
        assert rollout.batch_sizes == [1, 2, 3]
        done = await tick_until(rollout.id, {"succeeded", "rolled_back", "paused"}, timeout=90)
        assert done.state == "succeeded", done.reason
        await running_everywhere(controllers, "v2", timeout=5)

        members = await sync_to_async(list)(RolloutRobot.objects.filter(rollout=rollout).order_by("batch", "robot"))
        assert {m.status for m in members} == {"succeeded"}
        # Each batch started only after the batch before it had passed its soak.
        for earlier in members:
            for later in members:
                if later.batch == earlier.batch + 1:
                    assert later.started_at >= earlier.finished_at, (earlier.robot_id, later.robot_id)


async def test_a_bad_release_fails_its_canary_and_every_touched_robot_runs_the_old_version_again(
    cloud, tmp_path
) -> None:
    owner, robots = await fleet(5, {"site": "lab"})
    made = await release(owner, detector("v2", crash_after_s=3))
    async with agents(cloud, robots, tmp_path) as controllers:
        await old_version_running(robots)
        await running_everywhere(controllers, "v1")
        rollout = await start_rollout(owner, made, "site=lab", strategy={"first": 1, "soak_s": 6})
        done = await tick_until(rollout.id, {"succeeded", "rolled_back", "paused"}, timeout=90)
        assert done.state == "rolled_back", done.reason
        assert "crash" in done.reason or "failed" in done.reason, done.reason

        members = await sync_to_async(list)(RolloutRobot.objects.filter(rollout=rollout).order_by("batch"))
        touched = [m for m in members if m.touched]
        assert [m.batch for m in touched] == [0], "no robot past the canary is touched"
        assert all(m.status == "pending" for m in members if not m.touched)
        await running_everywhere(controllers, "v1", timeout=20)
