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


# The camera appends a numbered line to the Skill's volume every tenth of a second, going on from
# the file's last number: a swap that lost the volume, or a line, shows as a gap or a restart.
CAMERA = (
    'f="$BRIDGEOS_VOLUMES/data/frames.log"; n=$(tail -n 1 "$f" 2>/dev/null | cut -d " " -f 2); n=${n:-0}; '
    'while true; do n=$((n + 1)); echo "VERSION $n" >> "$f"; sleep 0.1; done'
)


def detector(version: str, *, crash_after_s: float | None = None) -> dict[str, Any]:
    """A Skill of two process components: a camera writing to the Skill's volume, and a detector (a crash: exits)."""
    detect = "exec sleep 600" if crash_after_s is None else f"sleep {crash_after_s}; exit 3"
    commands = {"camera": CAMERA.replace("VERSION", version), "detect": detect}
    components = {
        name: {
            "name": name,
            "location": "robot",
            "ros": False,
            "resources": {"cpu": 0.1, "ram": 16},
            "robot": {"command": ["sh", "-c", command]},
        }
        for name, command in commands.items()
    }
    config = {"skill": f"Detector {version}", "skill_id": SKILL, "components": components, "volumes": ["data"]}
    return parse_skill_config(config).model_dump(mode="json")


def frames(controller: RobotController) -> list[tuple[str, int]]:
    """The lines the camera wrote to the robot's volume: (version, number)."""
    path = controller.runtime.volumes_dir(SKILL) / "data" / "frames.log"
    if not path.exists():
        return []
    lines = [line.split() for line in path.read_text().splitlines()]
    return [(version, int(number)) for version, number in lines if number.isdigit()]


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
    owner, robots = await fleet(20, {"site": "lab"})
    made = await release(owner, detector("v2"))
    async with agents(cloud, robots, tmp_path) as controllers:
        await old_version_running(robots)
        await running_everywhere(controllers, "v1")
        rollout = await start_rollout(
            owner, made, "site=lab", strategy={"first": 1, "factor": 2, "soak_s": 1, "pause_s": 0}
        )
        assert rollout.batch_sizes == [1, 2, 4, 8, 5]
        done = await tick_until(rollout.id, {"succeeded", "rolled_back", "paused"}, timeout=150)
        assert done.state == "succeeded", done.reason
        await running_everywhere(controllers, "v2", timeout=5)

        members = await sync_to_async(list)(RolloutRobot.objects.filter(rollout=rollout).order_by("batch", "robot"))
        assert {m.status for m in members} == {"succeeded"}
        assert [sum(m.batch == b for m in members) for b in range(5)] == [1, 2, 4, 8, 5]
        # Each batch started only after every robot of the batch before it had passed its soak.
        for batch in range(1, 5):
            passed = max(m.finished_at for m in members if m.batch == batch - 1)
            started = min(m.started_at for m in members if m.batch == batch)
            assert started >= passed, (batch, started, passed)


async def test_a_bad_release_fails_its_canary_and_every_touched_robot_runs_the_old_version_again(
    cloud, tmp_path
) -> None:
    owner, robots = await fleet(20, {"site": "lab"})
    made = await release(owner, detector("v2", crash_after_s=5))
    async with agents(cloud, robots, tmp_path) as controllers:
        await old_version_running(robots)
        await running_everywhere(controllers, "v1")
        rollout = await start_rollout(owner, made, "site=lab", strategy={"first": 1, "soak_s": 8})
        done = await tick_until(rollout.id, {"succeeded", "rolled_back", "paused"}, timeout=90)
        assert done.state == "rolled_back", done.reason
        assert "crash" in done.reason or "failed" in done.reason, done.reason

        members = await sync_to_async(list)(RolloutRobot.objects.filter(rollout=rollout).order_by("batch"))
        touched = [m for m in members if m.touched]
        assert [m.batch for m in touched] == [0], "no robot past the canary is touched"
        assert all(m.status == "pending" for m in members if not m.touched)
        await running_everywhere(controllers, "v1", timeout=20)

        # Nothing the old version's camera wrote was lost across the swap and back: one unbroken count
        # through the release's lines, and the old version writing on after them.
        canary = next(c for c in controllers if c.settings.robot == touched[0].robot_id)
        await asyncio.sleep(0.5)
        written = frames(canary)
        assert [number for _, number in written] == list(range(1, len(written) + 1)), written[-20:]
        versions_in_order = [version for version, _ in written]
        first_v2, last_v2 = versions_in_order.index("v2"), len(versions_in_order) - versions_in_order[::-1].index("v2")
        assert set(versions_in_order[:first_v2]) == {"v1"} and first_v2 > 0
        assert versions_in_order[last_v2:] and set(versions_in_order[last_v2:]) == {"v1"}, "the old version is back"
        untouched = next(c for c in controllers if c.settings.robot != touched[0].robot_id)
        assert {version for version, _ in frames(untouched)} == {"v1"}
