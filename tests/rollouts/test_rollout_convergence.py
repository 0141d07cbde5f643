"""Robots that were offline, held or unhealthy by a metric, in rollouts driven against real agents."""

from __future__ import annotations

import asyncio
import time

import httpx
import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.controller import RobotController
from robots.models import Robot
from rollouts import rolling
from rollouts.models import RolloutRobot, UpdateHold
from skills.models import Skill
from tests.agent.conftest import agent_settings, configured
from tests.rollouts.test_rollout_agents import (
    SKILL,
    agents,
    detector,
    fleet,
    old_version_running,
    release,
    running_everywhere,
    start_rollout,
    tick_until,
    versions,
)

pytestmark = pytest.mark.django_db(transaction=True)


@sync_to_async
def statuses(rollout_id: int) -> dict[str, str]:
    return dict(RolloutRobot.objects.filter(rollout_id=rollout_id).values_list("robot_id", "status"))


@sync_to_async
def stored_version(robot_id: str) -> str:
    return Skill.objects.get(robot_id=robot_id, skill_id=SKILL).config["skill"].split()[-1]


async def wait_for(check, timeout: float, what: str, tick_rollout: int | None = None) -> None:
    from rollouts import executor

    deadline = time.monotonic() + timeout
    while not await check():
        if time.monotonic() > deadline:
            pytest.fail(f"{what} after {timeout} s")
        if tick_rollout is not None:
            await sync_to_async(executor.tick)()
        await asyncio.sleep(0.2)


async def test_a_robot_offline_during_its_batch_converges_when_it_reconnects(cloud, tmp_path) -> None:
    owner, robots = await fleet(3, {"site": "lab"})
    made = await release(owner, detector("v2"))
    async with agents(cloud, robots[:2], tmp_path) as controllers:
        # bot-02 ran v1, and its agent stopped (its robot switched off) before the rollout.
        late = RobotController(agent_settings(cloud, robots[2][0], robots[2][1], tmp_path / "late"))
        async with configured(late):
            await old_version_running(robots)
            await running_everywhere([*controllers, late], "v1")
        rollout = await start_rollout(owner, made, "site=lab", strategy={"first": 1, "soak_s": 1})

        async def others_done() -> bool:
            found = await statuses(rollout.id)
            return found["bot-00"] == found["bot-01"] == "succeeded" and found["bot-02"] == "offline"

        await wait_for(others_done, 60, "bot-00 and bot-01 not on the release", tick_rollout=rollout.id)
        assert await stored_version("bot-02") == "v2", "the offline robot's desired version is stored"
        assert (await sync_to_async(type(rollout).objects.get)(pk=rollout.id)).state == "running"

        back = RobotController(agent_settings(cloud, robots[2][0], robots[2][1], tmp_path / "late"))
        reconnected = time.monotonic()
        async with configured(back):
            await running_everywhere([back], "v2", timeout=15)
            converge_s = time.monotonic() - reconnected
            done = await tick_until(rollout.id, {"succeeded", "rolled_back"}, timeout=30)
            assert done.state == "succeeded", done.reason
            assert versions([*controllers, back]) == {"bot-00": "v2", "bot-01": "v2", "bot-02": "v2"}
        assert converge_s < 10, f"converged {converge_s:.1f} s after reconnecting"


async def test_a_robot_offline_through_a_rollback_stays_on_the_old_version(cloud, tmp_path) -> None:
    owner, robots = await fleet(3, {"site": "lab"})
    made = await release(owner, detector("v2", crash_after_s=2))
    async with agents(cloud, robots[:1], tmp_path) as controllers:
        await old_version_running(robots[:1])
        await running_everywhere(controllers, "v1")
        # A canary of two: bot-00 (online, fails) and bot-01 (offline: the release is stored for it).
        rollout = await start_rollout(owner, made, "site=lab", strategy={"first": 2, "soak_s": 5})
        done = await tick_until(rollout.id, {"rolled_back", "succeeded"}, timeout=60)
        assert done.state == "rolled_back", done.reason
        assert await statuses(rollout.id) == {"bot-00": "rolled_back", "bot-01": "rolled_back", "bot-02": "pending"}
        assert await stored_version("bot-01") == "v1", "the rollback put the offline robot's desired version back"
        await running_everywhere(controllers, "v1", timeout=20)

    back = RobotController(agent_settings(cloud, robots[1][0], robots[1][1], tmp_path / "back"))
    async with configured(back):
        await old_version_running(robots[1:2])
        await running_everywhere([back], "v1", timeout=15)


async def test_a_held_robot_waits_and_installs_once_released_or_past_its_deadline(cloud, tmp_path) -> None:
    owner, robots = await fleet(3, {"site": "lab"})
    made = await release(owner, detector("v2"))
    async with agents(cloud, robots, tmp_path) as controllers:
        await old_version_running(robots)
        await running_everywhere(controllers, "v1")
        robot = await sync_to_async(Robot.objects.get)(id="bot-00")
        await sync_to_async(rolling.hold_updates)(robot, "owner fleet-owner", 600, "mapping")
        short = await sync_to_async(Robot.objects.get)(id="bot-01")
        await sync_to_async(rolling.hold_updates)(short, "owner fleet-owner", 4, "docking")
        rollout = await start_rollout(owner, made, "site=lab", strategy={"first": 3, "soak_s": 1})

        async def held() -> bool:
            found = await statuses(rollout.id)
            return found["bot-02"] == "succeeded" and found["bot-00"] == "deferred"

        await wait_for(held, 30, "bot-02 not on the release while bot-00 waits", tick_rollout=rollout.id)
        assert versions(controllers)["bot-00"] == "v1", "a held robot keeps running its version"
        assert (await sync_to_async(type(rollout).objects.get)(pk=rollout.id)).state == "running"

        # bot-01's deadline passes: it installs without anyone releasing it.
        async def deadline_passed() -> bool:
            return (await statuses(rollout.id))["bot-01"] == "succeeded"

        await wait_for(
            deadline_passed, 30, "bot-01 not on the release past its hold's deadline", tick_rollout=rollout.id
        )
        assert versions(controllers)["bot-00"] == "v1"

        await sync_to_async(rolling.release_hold)(robot, "owner fleet-owner")
        done = await tick_until(rollout.id, {"succeeded", "rolled_back"}, timeout=30)
        assert done.state == "succeeded", done.reason
        await running_everywhere(controllers, "v2", timeout=5)


async def test_a_release_that_misses_a_metric_condition_of_its_gate_is_rolled_back(cloud, tmp_path) -> None:
    owner, robots = await fleet(2, {"site": "lab"})
    made = await release(owner, detector("v2"))
    async with agents(cloud, robots, tmp_path) as controllers:
        await old_version_running(robots)
        await running_everywhere(controllers, "v1")
        rollout = await start_rollout(
            owner,
            made,
            "site=lab",
            strategy={"first": 1, "soak_s": 2},
            gates={"conditions": ["cpu >= 0", "metric:detections_per_s > 5"]},
        )
        done = await tick_until(rollout.id, {"rolled_back", "succeeded"}, timeout=60)
        assert done.state == "rolled_back", done.reason
        assert "metric:detections_per_s > 5 (no points over the soak)" in done.reason, done.reason
        assert "cpu" not in done.reason.split("gate missed:")[1], "the robot's cpu met its condition"
        assert await statuses(rollout.id) == {"bot-00": "rolled_back", "bot-01": "pending"}
        await running_everywhere(controllers, "v1", timeout=20)


async def test_a_component_holds_its_robots_updates_through_the_components_api(cloud, tmp_path) -> None:
    owner, robots = await fleet(2, {"site": "lab"})
    made = await release(owner, detector("v2"))
    async with agents(cloud, robots, tmp_path) as controllers:
        await old_version_running(robots)
        await running_everywhere(controllers, "v1")
        # What a component reads from its environment: its Skill's Components API.
        api = controllers[0].skills[SKILL].supervisor.context["env"]["BRIDGEOS_MANAGER_URL"]
        async with httpx.AsyncClient(base_url=api, timeout=10) as http:
            refused = await http.post("/components/detect/hold", json={"seconds": -1})
            assert refused.status_code == 400 and refused.json()["field"] == "seconds"
            assert (await http.post("/components/nope/hold", json={"seconds": 60})).status_code == 404
            held = await http.post("/components/detect/hold", json={"seconds": 600, "reason": "mid-inspection"})
            assert held.status_code == 202, held.text

            async def hold_stored() -> bool:
                return await sync_to_async(UpdateHold.objects.filter(robot_id="bot-00").exists)()

            await wait_for(hold_stored, 10, "the component's hold did not reach the cloud")
            hold = await sync_to_async(UpdateHold.objects.get)(robot_id="bot-00")
            assert (hold.holder, hold.reason) == ("component detector/detect", "mid-inspection")

            rollout = await start_rollout(owner, made, "site=lab", strategy={"first": 2, "soak_s": 1})

            async def deferred() -> bool:
                found = await statuses(rollout.id)
                return found == {"bot-00": "deferred", "bot-01": "succeeded"}

            await wait_for(deferred, 30, "bot-00 not deferred while bot-01 installs", tick_rollout=rollout.id)
            assert versions(controllers)["bot-00"] == "v1"
            assert (await http.delete("/components/detect/hold")).status_code == 202

        done = await tick_until(rollout.id, {"succeeded", "rolled_back"}, timeout=30)
        assert done.state == "succeeded", done.reason
        await running_everywhere(controllers, "v2", timeout=5)
        assert not await sync_to_async(UpdateHold.objects.exists)()
