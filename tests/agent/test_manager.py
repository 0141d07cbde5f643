"""The Skill Manager against the real cloud: decisions, manual recommendations, moves, model persistence."""

from __future__ import annotations

import asyncio

import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.controller import RobotController
from bridgeos_agent.manager import DECISION_METRIC, SkillManager
from bridgeos_agent.skillconfig import parse_skill_config
from monitoring.models import Metric

from .test_controller import (
    SKILL,
    agent_settings,
    eventually,
    make_robot,
    running,
    running_workers,
    skill_config,
)

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(120)]


def movable_skill(interval: float = 5.0, threshold: float = 0.2) -> dict:
    config = skill_config(location="either", count=2)
    manager = {"policy": "energy", "decision_interval": interval, "threshold": threshold}
    config["manager"] = {**config.get("manager", {}), **manager}
    return parse_skill_config(config).model_dump(mode="json")


@sync_to_async
def decisions_stored(robot_id: str) -> list[Metric]:
    return list(Metric.objects.filter(robot_id=robot_id, name=DECISION_METRIC).order_by("ts"))


async def test_a_recommendation_moves_the_component_and_every_decision_reaches_the_cloud(cloud, tmp_path):
    # A threshold no saving reaches: only the recommendation moves anything.
    config = movable_skill(threshold=1e6)
    token, _ = await make_robot("man-1", config={"offloading": "auto"}, skill=config)
    controller = RobotController(agent_settings(cloud, "man-1", token, tmp_path / "agent"), plugins={})
    async with running(controller):
        await asyncio.wait_for(controller.config_from_cloud.wait(), 15)
        record = await controller.start_skill(parse_skill_config(config))
        assert set(record.locations.values()) == {"robot"}
        manager = SkillManager(controller, SKILL)
        with pytest.raises(ValueError, match="has no component"):
            manager.recommend("nope", "cloud")
        with pytest.raises(ValueError, match="must be 'robot' or 'cloud'"):
            manager.recommend("worker-1", "mars")
        manager.recommend("worker-1", "cloud")
        decisions = {d.component: d for d in await manager.step()}
        assert decisions["worker-1"].migrate and decisions["worker-1"].target == "cloud"
        assert record.locations == {"worker-0": "robot", "worker-1": "cloud"}
        assert set(running_workers(controller)) == {"worker-0"}
        stored = await eventually(lambda: decisions_stored("man-1"), what="decisions stored in the cloud")
        moved = [m for m in stored if m.component == "worker-1"]
        assert moved[0].labels["decision"] == "migrate" and moved[0].labels["policy"] == "energy"
        assert {"cost_robot", "cost_cloud", "location", "target"} <= set(moved[0].labels)
        assert [m.labels["decision"] for m in stored if m.component == "worker-0"] == ["stay"]


async def test_the_energy_policy_sends_movable_components_to_the_cloud(cloud, tmp_path):
    config = movable_skill()
    token, _ = await make_robot("man-4", skill=config)
    controller = RobotController(agent_settings(cloud, "man-4", token, tmp_path / "agent"), plugins={})
    async with running(controller):
        await asyncio.wait_for(controller.config_from_cloud.wait(), 15)
        record = await controller.start_skill(parse_skill_config(config))
        decisions = await SkillManager(controller, SKILL).step()
        # Energy spent on the robot (eq. 4.1) exceeds the cloud's radio-only share (eq. 4.2).
        assert all(d.migrate and d.estimated_reward > 0.2 for d in decisions), decisions
        assert set(record.locations.values()) == {"cloud"}
        assert running_workers(controller) == {}


async def test_nothing_moves_while_the_cloud_is_lost_or_the_mode_keeps_it(cloud, tmp_path):
    config = movable_skill()
    token, _ = await make_robot("man-2", config={"offloading": "robot"}, skill=config)
    controller = RobotController(agent_settings(cloud, "man-2", token, tmp_path / "agent"), plugins={})
    async with running(controller):
        await asyncio.wait_for(controller.config_from_cloud.wait(), 15)
        record = await controller.start_skill(parse_skill_config(config))
        manager = SkillManager(controller, SKILL)
        # Offloading "robot": movable components are kept on the robot, decision after decision.
        for _ in range(3):
            assert not any(d.migrate for d in await manager.step())
        assert set(record.locations.values()) == {"robot"}
        record.supervisor.context["cloud"] = "lost"
        manager.recommend("worker-0", "cloud")
        assert await manager.step() == []


async def test_the_manager_runs_by_itself_and_keeps_its_models_for_the_next_launch(cloud, tmp_path):
    config = movable_skill(interval=0.2)
    token, _ = await make_robot("man-3", skill=config)
    controller = RobotController(agent_settings(cloud, "man-3", token, tmp_path / "agent"))
    async with running(controller):
        await asyncio.wait_for(controller.config_from_cloud.wait(), 15)
        await controller.start_skill(parse_skill_config(config))
        manager = await eventually(lambda: controller.skills[SKILL].supervisor.context.get("manager"))
        await eventually(lambda: len(manager.last) == 2, what="decisions for both components")
        await eventually(lambda: manager.deciders["worker-0"].model.samples_seen >= 2, what="samples")
        await controller.stop_skill(SKILL)
    saved = tmp_path / "agent" / "models" / SKILL / "worker-0.pt"
    assert saved.exists()
    again = SkillManager(controller, SKILL)
    assert again._decider("worker-0").model.samples_seen >= 2


COMPONENT_SCRIPT = """
import json, os, time, urllib.request
url, me = os.environ["BRIDGEOS_MANAGER_URL"], os.environ["BRIDGEOS_COMPONENT"]
def post(path, body):
    request = urllib.request.Request(url + path, data=json.dumps(body).encode(), method="POST",
                                     headers={"Content-Type": "application/json"})
    return urllib.request.urlopen(request).status
peers = json.load(urllib.request.urlopen(url + "/components"))["components"]
post("/metrics", {"metrics": [{"name": "peers_seen", "value": len(peers), "component": me}]})
if me == "worker-1":
    post(f"/components/{me}/location", {"location": "cloud"})
time.sleep(600)
"""


async def test_components_reach_their_manager_and_a_recommendation_moves_one(cloud, tmp_path):
    import sys

    config = movable_skill(interval=0.3, threshold=1e6)
    for component in config["components"].values():
        component["robot"] = {"command": [sys.executable, "-c", COMPONENT_SCRIPT]}
        component["cloud"] = {"command": ["sleep", "600"]}
    token, _ = await make_robot("man-5", skill=config)
    controller = RobotController(agent_settings(cloud, "man-5", token, tmp_path / "agent"))
    async with running(controller):
        await asyncio.wait_for(controller.config_from_cloud.wait(), 15)
        record = await controller.start_skill(parse_skill_config(config))
        manager = record.supervisor.context["manager"]
        assert manager.api is not None and manager.api.base_url.startswith("http://127.0.0.1:")
        # Each component found the other through the Components API and said so.
        seen = await eventually(lambda: len(manager.store.latest(["peers_seen"])) == 2 and manager.store.latest())
        assert {p["value"] for p in seen if p["name"] == "peers_seen"} == {2.0}
        # The robot's own metrics are offered to components too (no component: the robot's).
        robot_cpu = await eventually(lambda: manager.store.latest(["cpu"], None), what="robot metrics offered")
        assert any(point.get("component") is None for point in robot_cpu)
        # worker-1 asked to run in the cloud: the manager's next decision moves it.
        await eventually(lambda: record.locations["worker-1"] == "cloud", what="worker-1 moved")
        assert record.locations["worker-0"] == "robot"
        stored = await eventually(lambda: _published("man-5"), what="published metric in the cloud")
        assert {m.component for m in stored} == {"worker-0", "worker-1"}
        await controller.stop_skill(SKILL)


@sync_to_async
def _published(robot_id: str) -> list[Metric]:
    rows = list(Metric.objects.filter(robot_id=robot_id, name="peers_seen", skill=SKILL))
    return rows if len(rows) == 2 else []


async def test_a_new_launch_starts_components_where_the_last_one_left_them(cloud, tmp_path):
    config = movable_skill(threshold=1e6)
    token, _ = await make_robot("man-6", skill=config)
    controller = RobotController(agent_settings(cloud, "man-6", token, tmp_path / "agent"), plugins={})
    async with running(controller):
        await asyncio.wait_for(controller.config_from_cloud.wait(), 15)
        record = await controller.start_skill(parse_skill_config(config))
        manager = SkillManager(controller, SKILL)
        manager.recommend("worker-1", "cloud")
        await manager.step()
        assert record.locations == {"worker-0": "robot", "worker-1": "cloud"}
        await controller.stop_skill(SKILL)
        assert set(record.locations.values()) == {None}
        record = await controller.start_skill(parse_skill_config(config))
        assert record.locations == {"worker-0": "robot", "worker-1": "cloud"}
        assert set(running_workers(controller)) == {"worker-0"}


def test_a_damaged_placement_file_means_no_previous_placement(tmp_path):
    from bridgeos_agent.controller import previous_placement

    folder = tmp_path / "models" / "s"
    folder.mkdir(parents=True)
    assert previous_placement(tmp_path, "s") == {}
    for text in ("{not json", "[1, 2]", '{"a": "mars", "b": "cloud"}'):
        (folder / "placement.json").write_text(text)
        assert previous_placement(tmp_path, "s") == ({"b": "cloud"} if "mars" in text else {})
