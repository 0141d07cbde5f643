"""The Skill Manager against the real cloud: decisions, manual recommendations, moves, model persistence."""

from __future__ import annotations

import asyncio
import logging
import time
from types import SimpleNamespace

import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.controller import RobotController
from bridgeos_agent.manager import DECISION_METRIC, USAGE_WINDOW, SkillManager
from bridgeos_agent.monitor import ResourceMonitor, SimulatedRobot
from bridgeos_agent.protocol import Event
from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_agent.traffic import ComponentTraffic
from monitoring.models import Event as LogEvent
from monitoring.models import Metric
from tests.conftest import eventually

from .conftest import SKILL, agent_settings, configured, make_robot, robot_agent, running_workers, skill_config

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(120)]


def movable_skill(interval: float = 5.0, threshold: float = 0.2) -> dict:
    config = skill_config(location="either", count=2)
    manager = {"policy": "energy", "decision_interval": interval, "threshold": threshold}
    config["manager"] = {**config.get("manager", {}), **manager}
    return parse_skill_config(config).model_dump(mode="json")


@sync_to_async
def decisions_stored(robot_id: str) -> list[Metric]:
    return list(Metric.objects.filter(robot_id=robot_id, name=DECISION_METRIC).order_by("ts"))


@sync_to_async
def marker_stored(robot_id: str) -> bool:
    return Metric.objects.filter(robot_id=robot_id, name="test.marker").exists()


@sync_to_async
def moves_logged(robot_id: str) -> list[LogEvent]:
    return list(LogEvent.objects.filter(robot_id=robot_id, kind="offloading_decision").order_by("ts"))


async def test_a_recommendation_moves_the_component_and_every_decision_reaches_the_cloud(cloud, tmp_path):
    # A threshold no saving reaches: only the recommendation moves anything.
    config = movable_skill(threshold=1e6)
    async with robot_agent(
        cloud, "man-1", tmp_path / "agent", config={"offloading": "auto"}, skill=config, plugins={}
    ) as controller:
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
        # The move is an event in the cloud's log, with its inputs, costs and outcome...
        moves = await eventually(lambda: moves_logged("man-1"), what="the move logged in the cloud")
        assert [(m.component, m.data["outcome"], m.data["target"]) for m in moves] == [("worker-1", "moved", "cloud")]
        move = moves[0].data
        assert move["policy"] == "energy" and move["reason"] == "recommendation" and move["duration_s"] >= 0
        assert {"cost_robot", "cost_cloud", "estimated_reward", "inputs", "decided_at"} <= set(move)
        assert move["inputs"]["location"] == "robot" and 0 <= move["inputs"]["cpu_available"] <= 1
        # ... and the decision to stay a metric point.
        stored = await eventually(lambda: decisions_stored("man-1"), what="decisions stored in the cloud")
        assert [(m.component, m.labels["decision"]) for m in stored] == [("worker-0", "stay")]
        assert {"cost_robot", "cost_cloud", "location", "target", "policy"} <= set(stored[0].labels)


async def test_a_move_that_fails_is_logged_as_failed_and_the_component_stays(cloud, tmp_path):
    config = movable_skill(threshold=1e6)
    config["components"]["worker-1"]["robot"] = {"command": ["/nonexistent/bridgeos-test-command"]}
    async with robot_agent(cloud, "man-7", tmp_path / "agent", skill=config, plugins={}) as controller:
        record = await controller.start_skill(parse_skill_config(config), starting=["worker-0"])
        await controller.place_component(record, "worker-1", location="cloud")
        manager = SkillManager(controller, SKILL)
        manager.recommend("worker-1", "robot")
        decisions = {d.component: d for d in await manager.step()}
        assert decisions["worker-1"].migrate and decisions["worker-1"].target == "robot"
        # Its cloud copy never stopped: it still runs there.
        assert record.locations["worker-1"] == "cloud" and record.statuses["worker-1"] == "running"
        moves = await eventually(lambda: moves_logged("man-7"), what="the failed move logged")
        assert moves[0].data["outcome"] == "failed" and moves[0].level == "warning"
        assert "bridgeos-test-command" in moves[0].data["error"]


class Router:
    """Stand in for the Skill Router: its traffic figures (pure data), and instances always ready to switch to."""

    settings = SimpleNamespace(ready_timeout=5.0)

    def __init__(self) -> None:
        self.figures: dict[str, ComponentTraffic] = {}
        self.asked: list[str] = []
        self.routed: dict[str, str | None] = {}

    def traffic(self, component: str) -> ComponentTraffic:
        self.asked.append(component)
        return self.figures[component]  # KeyError: the router routes nothing of it

    def active(self, component: str) -> str | None:
        return self.routed.get(component)

    def set_active(self, component: str, location: str | None) -> None:
        self.routed[component] = location

    async def wait_ready(self, component: str, location: str, timeout: float) -> bool:
        return True

    async def switch(self, component: str, location: str) -> None:
        self.routed[component] = location

    def set_container(self, component: str, location: str, container: dict) -> None:
        pass


def ros_skill(policy: str) -> dict:
    config = movable_skill(threshold=0.1)
    config["manager"]["policy"] = policy
    for component in config["components"].values():
        component["ros"] = True
        # Small enough to fit the simulated robot's link even at its lowest (5 Mbit/s): both start on the robot.
        component["resources"]["bandwidth"] = 1.0
    return parse_skill_config(config).model_dump(mode="json")


async def test_the_router_s_loss_rate_drives_the_performance_of_ros_components(cloud, tmp_path):
    config = ros_skill("performance")
    async with robot_agent(cloud, "man-8", tmp_path / "agent", skill=config, plugins={}) as controller:
        record = await controller.start_skill(parse_skill_config(config))
        assert set(record.locations.values()) == {"robot"}
        router = record.supervisor.context["router"] = Router()
        manager = SkillManager(controller, SKILL)
        # worker-0 loses 30 % of its messages on the robot; the cloud was never measured (0).
        router.figures["worker-0"] = ComponentTraffic(seconds=5, messages=100, dropped=30)
        decisions = {d.component: d for d in await manager.step()}
        assert set(router.asked) == {"worker-0", "worker-1"}  # worker-1: no routes, no figures
        assert decisions["worker-0"].features["loss"] == 0.3
        assert decisions["worker-0"].migrate and record.locations["worker-0"] == "cloud"
        assert not decisions["worker-1"].migrate and decisions["worker-1"].estimated_reward == 0.0
        # In the cloud it loses 5 %: the robot keeps its last measured 30 %, so it stays.
        router.figures["worker-0"] = ComponentTraffic(seconds=5, messages=100, dropped=5)
        decision = {d.component: d for d in await manager.step()}["worker-0"]
        assert decision.features["cost_robot"] == 0.3 and decision.features["cost_cloud"] == 0.05
        assert not decision.migrate and decision.estimated_reward == pytest.approx(-0.25)
        # A window without messages measures nothing: the last figures stand.
        router.figures["worker-0"] = ComponentTraffic(seconds=5)
        decision = {d.component: d for d in await manager.step()}["worker-0"]
        assert (decision.features["cost_robot"], decision.features["cost_cloud"]) == (0.3, 0.05)
        # Three decisions each, but a decision to stay reaches the cloud again only once it changed.
        # Frames are applied in order: once a marker sent after the decisions is stored, they all are.
        await controller.emit(Event.METRICS, {"metrics": [{"name": "test.marker", "value": 1.0, "ts": time.time()}]})
        await eventually(lambda: marker_stored("man-8"), what="the marker stored")
        stays = await decisions_stored("man-8")
        assert sorted((m.component, m.value) for m in stays) == [("worker-0", -0.25), ("worker-1", 0.0)]


async def test_the_router_s_bytes_and_the_declared_bandwidth_of_a_measured_component_drive_its_network_cost(
    cloud, tmp_path
):
    config = ros_skill("network")
    async with robot_agent(cloud, "man-9", tmp_path / "agent", skill=config, plugins={}) as controller:
        record = await controller.start_skill(parse_skill_config(config))
        assert set(record.locations.values()) == {"robot"}
        router = record.supervisor.context["router"] = Router()
        # The runtime measures the running processes (CPU and RAM); their bandwidth stays as declared.
        await eventually(
            lambda: {("workers", "worker-0"), ("workers", "worker-1")} <= set(controller.usage),
            what="components measured by the runtime",
        )
        # worker-0 talks mostly to the cloud, worker-1 only to robot peers.
        router.figures["worker-0"] = ComponentTraffic(seconds=10, bytes_robot=1_000_000, bytes_cloud=9_000_000)
        router.figures["worker-1"] = ComponentTraffic(seconds=10, bytes_robot=5_000_000)
        decisions = {d.component: d for d in await SkillManager(controller, SKILL).step()}
        # Eq. 4.3/4.4: 1 Mbit/s times the share of traffic with the other side.
        assert decisions["worker-0"].features["cost_robot"] == pytest.approx(0.9)
        assert decisions["worker-0"].features["cost_cloud"] == pytest.approx(0.1)
        assert decisions["worker-0"].migrate and record.locations["worker-0"] == "cloud"
        assert decisions["worker-1"].features["cost_robot"] == 0.0
        assert decisions["worker-1"].features["cost_cloud"] == pytest.approx(1.0)
        assert not decisions["worker-1"].migrate


async def test_cost_functions_read_the_robot_state_a_component_would_find_there(cloud, tmp_path):
    config = movable_skill(threshold=1e6)
    config["manager"].update(policy="custom", cost_functions={"robot": "cpu_free", "cloud": "ram_free"})
    config = parse_skill_config(config).model_dump(mode="json")
    async with robot_agent(cloud, "man-11", tmp_path / "agent", skill=config, plugins={}) as controller:
        record = await controller.start_skill(parse_skill_config(config), starting=["worker-0"])
        await controller.place_component(record, "worker-1", location="cloud")
        await eventually(lambda: controller.monitor.latest is not None, what="a sample of the robot")
        decisions = {d.component: d for d in await SkillManager(controller, SKILL).step()}
        free = controller.monitor.latest.free
        on_robot, in_cloud = decisions["worker-0"].features, decisions["worker-1"].features
        # On the robot: what is free now. In the cloud: what a move to the robot would leave (0.1 core, 16 MiB).
        assert on_robot["cost_robot"] == pytest.approx(free["cpu"])
        assert in_cloud["cost_robot"] == pytest.approx(free["cpu"] - 0.1)
        assert on_robot["cost_cloud"] - in_cloud["cost_cloud"] == pytest.approx(16)


async def test_a_cost_function_that_fails_skips_its_component_and_is_logged_once(cloud, tmp_path, caplog):
    config = movable_skill()
    config["manager"].update(policy="custom", cost_functions={"robot": "cpu / (battery - battery)", "cloud": "0"})
    config = parse_skill_config(config).model_dump(mode="json")
    async with robot_agent(cloud, "man-10", tmp_path / "agent", skill=config, plugins={}) as controller:
        record = await controller.start_skill(parse_skill_config(config))
        manager = SkillManager(controller, SKILL)
        with caplog.at_level(logging.WARNING, logger="bridgeos_agent.manager"):
            for _ in range(3):
                assert await manager.step() == []
        assert set(record.locations.values()) == {"robot"}
        warnings = [r.getMessage() for r in caplog.records if "cannot cost" in r.getMessage()]
        assert len(warnings) == 2, warnings
        assert any("worker-0" in w for w in warnings) and any("worker-1" in w for w in warnings)


async def test_the_energy_policy_sends_movable_components_to_the_cloud(cloud, tmp_path):
    config = movable_skill()
    async with robot_agent(cloud, "man-4", tmp_path / "agent", skill=config, plugins={}) as controller:
        record = await controller.start_skill(parse_skill_config(config))
        decisions = await SkillManager(controller, SKILL).step()
        # Energy spent on the robot (eq. 4.1) exceeds the cloud's radio-only share (eq. 4.2).
        assert all(d.migrate and d.estimated_reward > 0.2 for d in decisions), decisions
        assert set(record.locations.values()) == {"cloud"}
        assert running_workers(controller) == {}


async def test_nothing_moves_while_the_cloud_is_lost_or_the_mode_keeps_it(cloud, tmp_path):
    config = movable_skill()
    async with robot_agent(
        cloud, "man-2", tmp_path / "agent", config={"offloading": "robot"}, skill=config, plugins={}
    ) as controller:
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
    async with robot_agent(cloud, "man-3", tmp_path / "agent", skill=config) as controller:
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
    async with robot_agent(cloud, "man-5", tmp_path / "agent", skill=config) as controller:
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


async def test_a_cloud_copy_reaches_its_skills_manager_through_the_cloud(cloud, tmp_path):
    import httpx

    from skills.cloud.orchestration import cloud_spec
    from skills.models import CloudInstance

    config = movable_skill(interval=0.3, threshold=1e6)
    async with robot_agent(cloud, "man-9", tmp_path / "agent", skill=config) as controller:
        record = await controller.start_skill(parse_skill_config(config))
        record.supervisor.context["manager"].recommend("worker-1", "cloud")
        await eventually(lambda: record.locations["worker-1"] == "cloud", what="worker-1 moved")

        @sync_to_async
        def launch() -> tuple[str, str]:
            instance = CloudInstance.objects.select_related("component__skill__robot").get(
                component__skill__robot_id="man-9", component__component_id="worker-1"
            )
            return instance.token, cloud_spec(instance).env["BRIDGEOS_MANAGER_URL"]

        launch_token, url = await launch()
        # The copy's env names the cloud's relay with its launch token (BRIDGEOS_CLOUD_URL's default host).
        assert url == f"http://127.0.0.1:8000/api/cloud/manager/{launch_token}"
        base = f"{cloud.url}/api/cloud/manager/{launch_token}"
        async with httpx.AsyncClient(timeout=20) as http:
            listed = await http.get(f"{base}/components")
            assert listed.status_code == 200, listed.text
            where = {c["id"]: c["active_location"] for c in listed.json()["components"]}
            assert where == {"worker-0": "robot", "worker-1": "cloud"}
            posted = await http.post(f"{base}/metrics/frames_done", json={"value": 7})
            assert posted.status_code < 300, posted.text
            again = await http.get(f"{base}/metrics/frames_done")
            assert again.status_code == 200 and "7" in again.text
            # What the manager refuses, it refuses to the cloud copy too, and nothing else is reachable.
            refused = await http.get(f"{base}/components/nope")
            assert refused.status_code == 404
            assert (await http.get(f"{base}/secrets")).status_code == 400
            assert (await http.get(f"{cloud.url}/api/cloud/manager/0123456789abcdef/components")).status_code == 404
            assert (await http.post(f"{base}/metrics", content=b"not json")).status_code == 400
        await controller.stop_skill(SKILL)


@sync_to_async
def _published(robot_id: str) -> list[Metric]:
    rows = list(Metric.objects.filter(robot_id=robot_id, name="peers_seen", skill=SKILL))
    return rows if len(rows) == 2 else []


async def test_a_new_launch_starts_components_where_the_last_one_left_them(cloud, tmp_path):
    config = movable_skill(threshold=1e6)
    async with robot_agent(cloud, "man-6", tmp_path / "agent", skill=config, plugins={}) as controller:
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


async def test_a_move_in_flight_holds_up_no_other_decision_and_its_component_is_not_decided_for_again(cloud, tmp_path):
    config = movable_skill(threshold=1e6)
    async with robot_agent(
        cloud, "man-21", tmp_path / "agent", config={"offloading": "auto"}, skill=config, plugins={}
    ) as controller:
        record = await controller.start_skill(parse_skill_config(config))
        manager = SkillManager(controller, SKILL)
        manager.recommend("worker-1", "cloud")
        decisions = {d.component: d for d in await manager.step(wait=False)}
        assert decisions["worker-1"].migrate and decisions["worker-1"].target == "cloud"
        # Its cloud copy is still starting: it runs on the robot, and the next decisions are the others' only.
        assert record.locations["worker-1"] == "robot"
        assert [d.component for d in await manager.step(wait=False)] == ["worker-0"]
        await eventually(lambda: record.locations["worker-1"] == "cloud", what="the move landing")
        await eventually(lambda: not manager._moving, what="the move's task done")
        assert {d.component for d in await manager.step(wait=False)} == {"worker-0", "worker-1"}
        moves = await eventually(lambda: moves_logged("man-21"), what="the move logged in the cloud")
        assert [(m.component, m.data["outcome"]) for m in moves] == [("worker-1", "moved")]


async def test_a_component_s_cpu_is_the_mean_of_its_latest_measurements_on_the_robot(cloud, tmp_path):
    config = movable_skill(threshold=1e6)
    async with robot_agent(cloud, "man-22", tmp_path / "agent", skill=config, plugins={}) as controller:
        await controller.start_skill(parse_skill_config(config))
        manager = SkillManager(controller, SKILL)
        key = (SKILL, "worker-0")
        seen: list[float] = []
        # The first figure seen of a copy is left out (it may span the copy's start-up).
        previous = await eventually(lambda: controller.usage.get(key), what="worker-0 measured")
        assert manager._measured("worker-0", "robot") is None
        for _ in range(USAGE_WINDOW + 3):
            # Each of the runtime's measurements (a new one every sample) joins the window once.
            latest = await eventually(
                lambda previous=previous: (u := controller.usage.get(key)) is not None and u is not previous and u,
                what="a new measurement of worker-0",
            )
            seen.append(latest.cpu)
            averaged = manager._measured("worker-0", "robot")
            assert averaged.cpu == pytest.approx(sum(seen[-USAGE_WINDOW:]) / len(seen[-USAGE_WINDOW:]))
            # Asked again before a new measurement: the same mean (no measurement counts twice).
            assert manager._measured("worker-0", "robot").cpu == pytest.approx(averaged.cpu)
            previous = latest
        # Moved (here: asked where it runs in the cloud), the robot's figures of the copy it left say nothing.
        assert manager._measured("worker-0", "cloud") is None
        assert manager._measured("worker-0", "robot") is None  # back: a copy's first figure is left out


async def test_a_reading_wakes_who_waits_for_the_next_one_and_none_times_out():
    monitor = ResourceMonitor(SimulatedRobot(cpu=2, ram=1024, seed=3))
    waiting = asyncio.create_task(monitor.next_sample(5.0))
    await asyncio.sleep(0.05)
    assert not waiting.done()
    monitor.sample({})
    assert await asyncio.wait_for(waiting, 1) is True
    assert await monitor.next_sample(0.05) is False  # no reading came


async def test_the_manager_decides_on_each_fresh_reading_when_it_samples_as_often_as_it_decides(cloud, tmp_path):
    config = movable_skill(interval=0.2, threshold=1e6)
    token, _ = await make_robot("man-23", skill=config)
    controller = RobotController(agent_settings(cloud, "man-23", token, tmp_path / "agent", sample_interval=0.2))
    readings: list[float] = []
    sample = controller.monitor.sample

    def counted(*args, **kwargs):
        readings.append(time.monotonic())
        return sample(*args, **kwargs)

    controller.monitor.sample = counted
    async with configured(controller):
        await controller.start_skill(parse_skill_config(config))
        manager = await eventually(lambda: controller.skills[SKILL].supervisor.context.get("manager"))
        decided: set[float] = set()  # Decision.at: the manager's clock, time.monotonic
        while len(decided) < 8:
            await asyncio.sleep(0.02)
            if (last := manager.last.get("worker-0")) is not None:
                decided.add(last.at)
        await controller.stop_skill(SKILL)
    # Each decision came right after a reading (not up to a sample interval later), and on a new one each time.
    lags = [t - max(r for r in readings if r <= t) for t in sorted(decided)]
    assert sorted(lags)[len(lags) // 2] < 0.1, lags
    assert len({max(r for r in readings if r <= t) for t in decided}) == len(decided)
