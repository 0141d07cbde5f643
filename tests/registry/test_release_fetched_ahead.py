"""A rollout's robot fetches the release's image from the cloud's registry before its old version stops.

The real cloud (daphne), registry and Docker engine, and a real agent on the Docker runtime:
the robot runs version 1 of an image it pulled; a rollout of a release pinning version 2 shows
the robot `downloading` (its old version still running) with the bytes its pull reported, and
installs once the image is there.
"""

from __future__ import annotations

import asyncio
import time

import pytest
from asgiref.sync import sync_to_async

from tests.rollouts.test_rollout_agents import tick_until

from .test_docker_registry import PUSH_PROBE, run
from .test_pinning import own_registry  # noqa: F401 (a fixture used by name)
from .test_robot_pull import docker_agent, fleet, published, remove_robot_objects  # noqa: F401 (fixtures used by name)

pytestmark = [pytest.mark.docker, pytest.mark.django_db(transaction=True), pytest.mark.log_errors(PUSH_PROBE)]


def sleeper(image: str) -> dict:
    """A Skill of one component running ``image`` on the robot."""
    launch = {"image": image, "command": ["/bin/sleep", "600"]}
    return {
        "skill": "Sleeper",
        "skill_id": "sleeper",
        "components": {"nap": {"name": "Nap", "location": "robot", "robot": launch}},
    }


@sync_to_async
def owned(robot_id: str, config: dict):
    """Label Alice's robot, add version 1 of the Skill to it, and return Alice and that Skill."""
    from robots.models import Robot
    from skills.services import add_skill

    robot = Robot.objects.get(id=robot_id)
    Robot.objects.filter(id=robot_id).update(labels={"site": "lab"})
    return robot.owner, add_skill(robot, config)


@sync_to_async
def roll_out(owner, config: dict):
    """Make a release of ``config`` (its image pinned) and roll it out to the lab's robots: (release, rollout)."""
    from rollouts.rolling import create_rollout
    from rollouts.services import create_release
    from teams.services import personal_organization

    made = create_release(personal_organization(owner), config, user=owner)
    return made, create_rollout(made, "site=lab", user=owner, strategy={"soak_s": 1})


async def test_a_robot_downloads_the_release_while_its_old_version_runs_then_installs_it(
    daphne_server,
    own_registry,  # noqa: F811 (the cloud pins images of this registry)
    published,  # noqa: F811 (the fixture imported above)
    fleet,  # noqa: F811
    tmp_path,
):
    from bridgeos_agent.controller import RobotController
    from robots.services import push_to_robot
    from rollouts import executor
    from rollouts.models import RolloutRobot
    from skills.models import Component, Skill
    from skills.services import start_order

    old, new = published("alice/sleeper:1"), published("alice/sleeper:2")
    robot = fleet.alice_robot.name
    alice, skill = await owned(robot, sleeper(old))
    controller = RobotController(docker_agent(daphne_server, fleet, tmp_path))
    task = asyncio.create_task(controller.run())
    try:
        await asyncio.wait_for(controller.config_from_cloud.wait(), 20)
        await sync_to_async(push_to_robot)(robot, "skill_start", await sync_to_async(start_order)(skill))
        component = None
        for _ in range(300):
            component = await sync_to_async(Component.objects.get)(skill__robot_id=robot, component_id="nap")
            if component.status == "running" and (component.container.get("robot") or {}).get("id"):
                break
            await asyncio.sleep(0.1)
        assert component is not None and component.status == "running", component and component.message
        old_container = component.container["robot"]["id"]

        made, rollout = await roll_out(alice, sleeper(new))
        pinned = made.config["components"]["nap"]["robot"]["image"]
        assert "@sha256:" in pinned

        seen: list[tuple[str, str]] = []  # (the robot's rollout status, its Skill's status) after each step
        deadline = time.monotonic() + 90
        while time.monotonic() < deadline:
            await sync_to_async(executor.tick)()
            member = await sync_to_async(RolloutRobot.objects.get)(rollout=rollout)
            running = await sync_to_async(lambda: Skill.objects.get(robot_id=robot, skill_id="sleeper").status)()
            seen.append((member.status, running))
            if member.status in ("succeeded", "failed"):
                break
            await asyncio.sleep(0.2)
        assert member.status == "succeeded", (member.reason, seen)
        downloading = [skill_status for status, skill_status in seen if status == "downloading"]
        assert downloading, seen
        assert set(downloading) == {"running"}, "the old version runs on while the new image comes"
        # The bytes the robot's pull reported of the new image's compressed layers, all of them.
        assert member.bytes_total > 0 and member.bytes_done == member.bytes_total, (
            member.bytes_done,
            member.bytes_total,
        )

        done = await tick_until(rollout.id, {"succeeded", "rolled_back"}, timeout=10)
        assert done.state == "succeeded", done.reason
        component = await sync_to_async(Component.objects.get)(skill__robot_id=robot, component_id="nap")
        running = component.container["robot"]
        assert running["id"] != old_container
        # The engine runs the pinned digest of version 2.
        inspected = run("docker", "inspect", "--format", "{{.Image}}", running["id"])
        wanted = run("docker", "image", "inspect", "--format", "{{.Id}}", pinned)
        assert inspected.returncode == 0 and inspected.stdout.strip() == wanted.stdout.strip(), inspected.stderr
    finally:
        controller.stop()
        await asyncio.wait_for(task, 30)
        remove_robot_objects(robot)
        run("docker", "rmi", "-f", old, new)
