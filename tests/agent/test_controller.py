"""The Robot Controller against the real cloud (daphne, PostgreSQL, Redis) with the process runtime."""

from __future__ import annotations

import asyncio
import itertools
import os
import subprocess
import sys
import time

import httpx
import psutil
import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.controller import RobotController
from bridgeos_agent.monitor import SimulatedRobot
from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.skillconfig import parse_skill_config
from robots.models import Robot
from robots.services import create_robot
from skills.models import CloudInstance, Component
from tests.agent.conftest import (
    SKILL,
    agent_settings,
    configured,
    make_robot,
    robot_agent,
    running,
    running_workers,
    skill_config,
)
from tests.conftest import BIN, eventually

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(240)]


@sync_to_async
def stored_metrics(robot_id: str) -> tuple[int, int]:
    """Return (rows, rows beyond the first of each identical point) stored for a robot."""
    from django.db import connection

    with connection.cursor() as cursor:
        cursor.execute(
            "SELECT count(*), count(*) - count(DISTINCT (name, ts, coalesce(skill, ''), coalesce(component, '')))"
            " FROM monitoring_metric WHERE robot_id = %s",
            [robot_id],
        )
        return cursor.fetchone()


async def metric_rows(robot_id: str) -> int:
    return (await stored_metrics(robot_id))[0]


@sync_to_async
def component_rows(robot_id: str) -> dict[str, tuple[str, str | None]]:
    return {
        c.component_id: (c.status, c.active_location)
        for c in Component.objects.filter(skill__robot_id=robot_id, skill__skill_id=SKILL)
    }


async def test_connects_receives_its_config_and_reports_metrics(cloud, tmp_path):
    async with robot_agent(cloud, "ctl-1", tmp_path / "agent", config={"offloading": "manual"}) as controller:
        assert controller.config.offloading == "manual"
        robot = await sync_to_async(Robot.objects.get)(id="ctl-1")
        assert robot.connected
        assert await eventually(lambda: metric_rows("ctl-1"), what="metrics stored") > 0
    # The config from the cloud is kept on disk for the next start.
    assert '"offloading": "manual"' in (tmp_path / "agent" / "state.json").read_text()


@sync_to_async
def metric_frames(robot_id: str) -> tuple[list[float], int]:
    """Return the commit times of a robot's stored metrics frames, in order, and how many sample times its points have."""
    from monitoring.models import IngestedFrame, Metric

    frames = IngestedFrame.objects.filter(robot_id=robot_id).order_by("created").values_list("created", flat=True)
    samples = Metric.objects.filter(robot_id=robot_id).values("ts").distinct().count()
    return [created.timestamp() for created in frames], samples


async def test_a_report_interval_sends_the_samples_taken_meanwhile_in_one_frame(cloud, tmp_path):
    # Five samples a second, a frame a second: the cloud's cost is per frame, so a large fleet reports seldom.
    async with robot_agent(cloud, "ctl-batch", tmp_path / "agent", report_interval=1.0):
        frames, samples = await eventually(
            lambda: _at_least(metric_frames("ctl-batch"), 5), timeout=20, what="five metrics frames stored"
        )
    gaps = [later - earlier for earlier, later in itertools.pairwise(frames)]
    # About a second apart on average (one frame's commit can be late and the next's on time).
    assert 0.7 <= sum(gaps) / len(gaps) <= 1.5, gaps
    # A frame a sample would have as many frames as sample times; here each frame carries about five.
    assert samples >= 3 * len(frames), (samples, len(frames))


async def _at_least(frames_coroutine, count: int):
    frames, samples = await frames_coroutine
    return (frames, samples) if len(frames) >= count else None


async def test_a_skill_started_through_the_api_runs_on_the_robot(cloud, tmp_path):
    token, api_token = await make_robot("ctl-2", skill=skill_config())
    controller = RobotController(agent_settings(cloud, "ctl-2", token, tmp_path / "agent"))
    async with configured(controller):
        async with httpx.AsyncClient(base_url=cloud.url, headers={"Authorization": f"Token {api_token}"}) as api:
            response = await api.post(f"/api/robot/ctl-2/skill/{SKILL}/start", params={"wait": 10})
        assert response.status_code == 200, response.text
        assert response.json()["accepted"] is True
        pids = await eventually(lambda: len(running_workers(controller)) == 2 and running_workers(controller))
        rows = await eventually(
            lambda: _all_running(component_rows("ctl-2")), what="components reported running on the robot"
        )
        assert rows == {"worker-0": ("running", "robot"), "worker-1": ("running", "robot")}
        for pid in pids.values():
            assert os.environ.get("BRIDGEOS_SKILL") is None  # the contract env is the child's, not ours
            env = psutil.Process(pid).environ()
            assert env["BRIDGEOS_SKILL"] == SKILL and env["BRIDGEOS_LOCATION"] == "robot"
        # Stopping through the API stops the processes.
        async with httpx.AsyncClient(base_url=cloud.url, headers={"Authorization": f"Token {api_token}"}) as api:
            response = await api.post(f"/api/robot/ctl-2/skill/{SKILL}/stop", params={"wait": 10})
        assert response.status_code == 200, response.text
        await eventually(lambda: not running_workers(controller), what="workers stopped")
        for pid in pids.values():
            await eventually(lambda pid=pid: not psutil.pid_exists(pid), what=f"pid {pid} gone")


async def _all_running(rows_coroutine) -> dict | None:
    rows = await rows_coroutine
    return rows if rows and all(status == "running" for status, _ in rows.values()) else None


async def test_a_cloud_outage_loses_and_duplicates_no_metric(cloud, tmp_path):
    # 20 s, a hundred samples held; BRIDGEOS_TEST_OUTAGE_S=60 runs the minute of the original claim.
    outage = float(os.environ.get("BRIDGEOS_TEST_OUTAGE_S", "20"))
    token, _ = await make_robot("ctl-3")
    controller = RobotController(agent_settings(cloud, "ctl-3", token, tmp_path / "agent"))
    async with running(controller):
        await eventually(lambda: metric_rows("ctl-3"), what="metrics flowing")
        cloud.stop()
        await asyncio.sleep(outage)
        held = controller.outbox.stats()
        assert held.metric_frames >= outage / 0.2 * 0.8, held  # every sample was kept
        cloud.start()
        await eventually(lambda: len(controller.outbox) == 0, timeout=60, what="the backlog delivered")
        sent = controller.metric_points_sent
    rows, duplicates = await stored_metrics("ctl-3")
    assert duplicates == 0
    assert rows == sent, f"{sent} points sent, {rows} stored"


async def test_a_restarted_agent_delivers_its_backlog_and_readopts_its_components(cloud, tmp_path):
    token, api_token = await make_robot("ctl-4", skill=skill_config())
    data_dir = tmp_path / "agent"
    # This agent leaves its components running, as a real agent does, for the next to adopt.
    first = RobotController(agent_settings(cloud, "ctl-4", token, data_dir, stop_components_on_exit=False))
    async with running(first):
        await asyncio.wait_for(first.config_from_cloud.wait(), 15)
        async with httpx.AsyncClient(base_url=cloud.url, headers={"Authorization": f"Token {api_token}"}) as api:
            response = await api.post(f"/api/robot/ctl-4/skill/{SKILL}/start", params={"wait": 10})
        assert response.status_code == 200, response.text
        pids = await eventually(lambda: len(running_workers(first)) == 2 and running_workers(first))
        cloud.stop()
        await asyncio.sleep(3)
        backlog = len(first.outbox)
        sent_before = first.metric_points_sent
        assert backlog > 0
    # The agent is gone; its components and its backlog are not.
    assert all(psutil.pid_exists(pid) for pid in pids.values())
    cloud.start()
    second = RobotController(agent_settings(cloud, "ctl-4", token, data_dir))
    async with running(second):
        adopted = await eventually(lambda: running_workers(second), what="components re-adopted")
        assert adopted == pids, "the same processes are adopted, not new ones"
        await eventually(lambda: len(second.outbox) == 0, timeout=60, what="the backlog delivered")
        # The skill was running: once the cloud's config arrived it is running again, same pids.
        await eventually(lambda: second.skills[SKILL].status == "running", what="skill running again")
        assert running_workers(second) == pids
        sent = sent_before + second.metric_points_sent
        await second.stop_skill(SKILL)
    rows, duplicates = await stored_metrics("ctl-4")
    assert duplicates == 0
    assert rows == sent


async def test_takeover_runs_cloud_components_on_the_robot_and_reverts(cloud, tmp_path):
    config = {"offloading": "cloud", "heartbeat_interval": 0.5, "connection_lost_after": 2.0}
    token, api_token = await make_robot("ctl-5", config=config, skill=skill_config(location="either", count=3))
    controller = RobotController(agent_settings(cloud, "ctl-5", token, tmp_path / "agent"))
    async with configured(controller):
        async with httpx.AsyncClient(base_url=cloud.url, headers={"Authorization": f"Token {api_token}"}) as api:
            response = await api.post(f"/api/robot/ctl-5/skill/{SKILL}/start", params={"wait": 10})
        assert response.status_code == 200, response.text
        # Offloading "cloud": every movable component is handed to the cloud, none runs here.
        await eventually(lambda: _all_at(component_rows("ctl-5"), "cloud", 3), what="components placed in the cloud")
        # The cloud's Celery worker launched each cloud copy and reported it running.
        rows = await eventually(
            lambda: _all_running_at(component_rows("ctl-5"), "cloud", 3), timeout=30, what="cloud copies running"
        )
        assert set(rows.values()) == {("running", "cloud")}
        assert running_workers(controller) == {}
        cloud.stop()
        await eventually(lambda: len(running_workers(controller)) == 3, timeout=15, what="takeover")
        assert controller.takeover_components() == {SKILL: ["worker-0", "worker-1", "worker-2"]}
        events = controller.skills[SKILL].supervisor.events
        assert await asyncio.wait_for(events.get(), 1) == "connection_lost"
        cloud.start()
        await eventually(lambda: not running_workers(controller), timeout=30, what="revert")
        assert await asyncio.wait_for(events.get(), 5) == "connection_established"
        assert controller.takeover_components() == {}
        assert set(controller.skills[SKILL].locations.values()) == {"cloud"}


async def _all_running_at(rows_coroutine, location: str, count: int) -> dict | None:
    rows = await _all_at(rows_coroutine, location, count)
    return rows if rows and all(status == "running" for status, _ in rows.values()) else None


async def _all_at(rows_coroutine, location: str, count: int) -> dict | None:
    rows = await rows_coroutine
    if len(rows) == count and all(where == location for _, where in rows.values()):
        return rows
    return None


async def test_a_component_that_does_not_fit_moves_a_movable_one_to_the_cloud(cloud, tmp_path):
    # A 1-core robot runs a movable 0.8-core component; a robot-only 0.5-core one then asks for room.
    config = {"resources": {"cpu": 1.0}, "threshold": 10.0, "offloading": "robot"}
    either = skill_config(location="either", count=1, cpu=0.8)
    either["components"]["worker-1"] = {**either["components"]["worker-0"], "name": "Pinned", "location": "robot"}
    either["components"]["worker-1"]["resources"] = {"cpu": 0.5, "ram": 16}
    del either["components"]["worker-1"]["cloud"]
    token, _ = await make_robot("ctl-6", config=config, skill=either)
    settings = agent_settings(cloud, "ctl-6", token, tmp_path / "agent")
    settings.simulated = SimulatedRobot(cpu=1.0, ram=4096, seed=2)
    controller = RobotController(settings)
    async with configured(controller):
        record = await controller.start_skill(parse_skill_config(either), starting=["worker-0"])
        assert record.locations["worker-0"] == "robot"
        where = await controller.place_component(record, "worker-1")
        assert where == "robot"
        assert record.locations == {"worker-0": "cloud", "worker-1": "robot"}
        assert set(running_workers(controller)) == {"worker-1"}
        assert record.statuses == {"worker-0": CS.RUNNING, "worker-1": CS.RUNNING}
        # The moved component was migrated, not dropped: its cloud copy ran before the robot's stopped.
        instance = await sync_to_async(CloudInstance.objects.get)(
            component__skill__robot_id="ctl-6", component__component_id="worker-0"
        )
        assert instance.status == "running"


async def test_the_robot_reports_its_ros_master_or_gets_the_clouds(cloud, tmp_path):
    token, _ = await make_robot("ros-1")
    controller = RobotController(agent_settings(cloud, "ros-1", token, tmp_path / "one"))
    async with running(controller):
        await asyncio.wait_for(controller.connected.wait(), 15)
        # make test starts a roscore on the default port.
        assert controller.local_ros_master == controller.ros_master == "http://127.0.0.1:11311"
        robot = await sync_to_async(Robot.objects.get)(id="ros-1")
        assert robot.ros_master == "http://127.0.0.1:11311"
    cloud.stop()
    cloud.env["BRIDGEOS_CLOUD_ROS_MASTER"] = "http://10.9.0.1:11311"
    cloud.start()
    token, _ = await make_robot("ros-2")
    settings = agent_settings(cloud, "ros-2", token, tmp_path / "two", detect_ros_master=False)
    controller = RobotController(settings)
    async with running(controller):
        await asyncio.wait_for(controller.connected.wait(), 15)
        assert controller.local_ros_master is None
        assert controller.ros_master == "http://10.9.0.1:11311"
        spec = controller.component_spec(controller.skills.setdefault(SKILL, _record(skill_config())), "worker-0")
        assert spec.env["ROS_MASTER_URI"] == "http://10.9.0.1:11311"


def _record(config: dict):
    from bridgeos_agent.controller import SkillRecord

    return SkillRecord(config=parse_skill_config(config))


def test_run_with_a_wrong_token_exits_with_a_clear_message(daphne_server, tmp_path):
    result = subprocess.run(
        [
            str(BIN / "bridgeos-agent"),
            "run",
            "--master",
            daphne_server.ws_url,
            "--robot",
            "nobody",
            "--token",
            "brt_wrong",
            "--data-dir",
            str(tmp_path / "agent"),
            "--simulate",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 3, result.stderr
    assert "refused this robot" in result.stderr and "--token" in result.stderr


def test_doctor_says_what_works_and_what_does_not(daphne_server, tmp_path):
    _, token = create_robot("doc-1", _owner("doctor-owner"))
    result = subprocess.run(
        [str(BIN / "bridgeos-agent"), "doctor", "--master", daphne_server.ws_url, "--robot", "doc-1", "--token", token],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert "ok    cloud reachable" in result.stdout
    assert "ok    robot doc-1 is accepted" in result.stdout
    wrong = subprocess.run(
        [str(BIN / "bridgeos-agent"), "doctor", "--master", "ws://127.0.0.1:9", "--robot", "doc-1", "--token", "x"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert wrong.returncode == 1
    assert "FAIL  cannot reach the cloud at ws://127.0.0.1:9" in wrong.stdout


def _owner(name: str):
    from django.contrib.auth import get_user_model

    return get_user_model().objects.create_user(name)


def test_the_agent_exits_cleanly_on_sigterm(daphne_server, tmp_path):
    _, token = create_robot("sig-1", _owner("sig-owner"))
    process = subprocess.Popen(
        [
            str(BIN / "bridgeos-agent"),
            "run",
            "--master",
            daphne_server.ws_url,
            "--robot",
            "sig-1",
            "--token",
            token,
            "--data-dir",
            str(tmp_path / "agent"),
            "--simulate",
        ],
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 30
    while not Robot.objects.get(id="sig-1").connected:
        assert time.monotonic() < deadline and process.poll() is None, "the agent did not connect"
        time.sleep(0.1)
    # The cloud marks the robot connected before the agent logs it: wait for the agent's own line.
    seen = []
    while not any("connected to the cloud" in line for line in seen):
        line = process.stderr.readline()
        assert line, f"the agent exited before saying it connected: {''.join(seen)}"
        seen.append(line)
    process.terminate()
    _, err = process.communicate(timeout=30)
    err = "".join(seen) + err
    assert process.returncode == 0, err
    assert "connected to the cloud" in err and "stopped" in err
    assert sys.executable  # the agent ran from this venv's console script


async def test_a_migration_moves_the_component_and_back(cloud, tmp_path):
    token, api_token = await make_robot("mig-1", skill=skill_config(location="either", count=1))
    controller = RobotController(agent_settings(cloud, "mig-1", token, tmp_path / "agent"))
    headers = {"Authorization": f"Token {api_token}"}
    async with configured(controller), httpx.AsyncClient(base_url=cloud.url, headers=headers) as api:
        assert (await api.post(f"/api/robot/mig-1/skill/{SKILL}/start", params={"wait": 10})).status_code == 200
        await eventually(lambda: running_workers(controller), what="worker on the robot")
        # The API moves a component "to the other side" of where the cloud knows it runs.
        await eventually(lambda: _all_at(component_rows("mig-1"), "robot", 1), what="the cloud knows where it runs")
        path = f"/api/robot/mig-1/skill/{SKILL}/component/worker-0/migrate"
        assert (await api.post(path, params={"wait": 10})).status_code == 200
        # The API answers once the robot moved it: the cloud copy runs, the robot copy is gone.
        rows = await eventually(lambda: _all_at(component_rows("mig-1"), "cloud", 1), what="moved to the cloud")
        assert rows == {"worker-0": ("running", "cloud")}
        await eventually(lambda: not running_workers(controller), what="robot copy stopped")
        assert (await api.post(path, params={"wait": 10})).status_code == 200
        rows = await eventually(lambda: _all_at(component_rows("mig-1"), "robot", 1), what="back on the robot")
        await eventually(lambda: running_workers(controller), what="robot copy running again")
        await asyncio.sleep(0.5)  # the cloud copy's stop arrives after the move: it must not undo it
        assert await component_rows("mig-1") == {"worker-0": ("running", "robot")}
