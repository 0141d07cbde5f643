"""The cloud's process runtime with a real two-process Celery worker: requests racing, migrations, volume sync.

The robot is the real agent over real sockets; the cloud copies are real processes, found by
the marker in their environment. Migrations go through the REST API as an operator would
send them, and a dashboard client watches what the cloud broadcasts meanwhile.
"""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import httpx
import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.controller import RobotController
from bridgeos_agent.protocol import Event
from bridgeos_agent.skillconfig import parse_skill_config
from monitoring.models import Event as LogEvent
from skills.models import CloudInstance, Component
from tests.agent.conftest import agent_settings, configured, make_robot, running_workers
from tests.cloud.wsutil import client_link
from tests.conftest import eventually

from .conftest import make_stack, observe_async

pytestmark = [
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(180),
    pytest.mark.usefixtures("robots_disconnect_before_flush"),
]

SKILL = "workers"
SLEEP = {"command": ["sleep", "600"]}
# In the cloud: copies what the robot put in the volume, so the robot can see the cloud copy read it.
MIRROR = (
    'while true; do f="$BRIDGEOS_VOLUMES/data/from-robot.txt"; '
    '[ -f "$f" ] && ! cmp -s "$f" "$BRIDGEOS_VOLUMES/data/seen-by-cloud.txt" && '
    'cp "$f" "$BRIDGEOS_VOLUMES/data/seen-by-cloud.txt"; sleep 0.2; done'
)


@pytest.fixture(scope="module")
def stack(django_db_setup, django_db_blocker, tmp_path_factory):
    yield from make_stack("process", tmp_path_factory.mktemp("process"))


def skill(volumes: list[str] | None = None, **components: dict) -> dict:
    config = {"skill": "Workers", "skill_id": SKILL, "components": components, "volumes": volumes or []}
    return parse_skill_config(config).model_dump(mode="json")


def component(location: str, *, robot: dict | None = SLEEP, cloud: dict | None = SLEEP, **extra) -> dict:
    spec: dict = {"name": extra.pop("name", "C"), "location": location, "ros": False, **extra}
    if location != "cloud":
        spec["robot"] = robot
    if location != "robot":
        spec["cloud"] = cloud
    return spec


async def copies_of(stack, robot_id: str, name: str) -> list:
    return [o for o in await observe_async(stack.runtime) if o.robot == robot_id and o.component == name]


@sync_to_async
def instance_of(robot_id: str, name: str) -> CloudInstance | None:
    return CloudInstance.objects.filter(component__skill__robot_id=robot_id, component__component_id=name).first()


@sync_to_async
def row(robot_id: str, name: str) -> tuple[str, str]:
    found = Component.objects.get(skill__robot_id=robot_id, component_id=name)
    return found.status, found.active_location


async def test_start_stop_start_in_quick_succession_leaves_exactly_one_cloud_process(stack, tmp_path):
    config = skill(worker=component("cloud", name="Worker"))
    token, _ = await make_robot("race-1", skill=config)
    controller = RobotController(agent_settings(stack.server, "race-1", token, tmp_path / "agent"), plugins={})
    data = {"skill": SKILL, "component": "worker", "location": "cloud"}
    async with configured(controller):
        await controller.start_skill(parse_skill_config(config), starting=[])
        # Bursts of start/stop/start reach two worker processes at once.
        for _ in range(3):
            for event in (Event.COMPONENT_START, Event.COMPONENT_STOP, Event.COMPONENT_START):
                await controller.emit(event, data)

        async def settled_running() -> bool:
            instance = await instance_of("race-1", "worker")
            return instance is not None and instance.status == "running" and instance.desired == "running"

        await eventually(settled_running, timeout=60, what="the last start done")
        # Let every overtaken task run out: none of them may launch another copy.
        await asyncio.sleep(3)
        copies = await copies_of(stack, "race-1", "worker")
        assert len(copies) == 1, copies
        assert (await instance_of("race-1", "worker")).container["id"] == str(copies[0].id)

        # And a burst ending with a stop leaves none.
        for event in (Event.COMPONENT_STOP, Event.COMPONENT_START, Event.COMPONENT_STOP):
            await controller.emit(event, data)
        await eventually(lambda: _stopped("race-1", "worker"), timeout=60, what="the last stop done")
        await asyncio.sleep(3)
        assert await copies_of(stack, "race-1", "worker") == []


async def _stopped(robot_id: str, name: str) -> bool:
    instance = await instance_of(robot_id, name)
    return instance is not None and instance.status == "stopped" and instance.desired == "stopped"


async def test_a_migration_goes_robot_to_cloud_and_back_with_the_right_status_throughout(stack, tmp_path):
    config = skill(mover=component("either", name="Mover"))
    token, api_token = await make_robot("mig-2", skill=config)
    controller = RobotController(agent_settings(stack.server, "mig-2", token, tmp_path / "agent"), plugins={})
    headers = {"Authorization": f"Token {api_token}"}
    path = f"/api/robot/mig-2/skill/{SKILL}/component/mover/migrate"
    async with configured(controller), httpx.AsyncClient(base_url=stack.url, headers=headers, timeout=60) as api:
        await controller.start_skill(parse_skill_config(config))
        await eventually(lambda: _row_is("mig-2", "mover", ("running", "robot")), what="running on the robot")
        watcher = await client_link(stack.server, api_token)
        try:
            answer = await api.post(path, params={"wait": 60})
            assert answer.status_code == 200 and answer.json()["accepted"], answer.text
            assert await row("mig-2", "mover") == ("running", "cloud")
            assert not running_workers(controller)
            assert [c.status for c in await copies_of(stack, "mig-2", "mover")] == ["running"]

            answer = await api.post(path, params={"wait": 60})
            assert answer.status_code == 200 and answer.json()["accepted"], answer.text
            assert await row("mig-2", "mover") == ("running", "robot")
            assert set(running_workers(controller)) == {"mover"}
            await eventually(lambda: _stopped("mig-2", "mover"), what="the cloud copy retired")
            assert await copies_of(stack, "mig-2", "mover") == []

            seen = await _statuses(watcher, "mover", until=("running", "robot"), after=1)
        finally:
            await watcher.close()
    # The dashboard saw it migrate from the robot, run in the cloud, migrate back and run on the robot,
    # and never saw the cloud copy's start as the component's own state while the robot copy was active.
    assert seen[:4] == [("migrating", "robot"), ("running", "cloud"), ("migrating", "cloud"), ("running", "robot")]


async def _row_is(robot_id: str, name: str, wanted: tuple[str, str]) -> bool:
    return await row(robot_id, name) == wanted


async def _statuses(link, name: str, *, until: tuple[str, str], after: int) -> list[tuple[str, str]]:
    """Collect the component_status frames a client received for a component, up to the `after`-th `until`."""
    seen: list[tuple[str, str]] = []
    hits = 0
    while hits < after:
        frame = await link.next(Event.COMPONENT_STATUS, timeout=30)
        if frame.data.get("component") == name:
            seen.append((frame.data["status"], frame.data.get("location")))
            hits += seen[-1] == until
    return [pair for pair in seen if pair[0] in ("migrating", "running")]


async def test_a_failed_cloud_start_rolls_the_migration_back_and_says_why(stack, tmp_path):
    config = skill(mover=component("either", name="Mover", cloud={"command": ["/nonexistent/mover-binary"]}))
    token, api_token = await make_robot("mig-3", skill=config)
    controller = RobotController(agent_settings(stack.server, "mig-3", token, tmp_path / "agent"), plugins={})
    headers = {"Authorization": f"Token {api_token}"}
    async with configured(controller), httpx.AsyncClient(base_url=stack.url, headers=headers, timeout=60) as api:
        await controller.start_skill(parse_skill_config(config))
        await eventually(lambda: _row_is("mig-3", "mover", ("running", "robot")), what="running on the robot")
        pid = running_workers(controller)["mover"]

        answer = await api.post(f"/api/robot/mig-3/skill/{SKILL}/component/mover/migrate", params={"wait": 60})
        assert answer.status_code == 200, answer.text
        body = answer.json()
        assert body["accepted"] is False
        reason = body["reply"]["data"]["message"]
        assert "the cloud could not run 'mover'" in reason and "/nonexistent/mover-binary" in reason

        # Still on the robot, the same process, and the cloud knows why the move failed.
        assert running_workers(controller) == {"mover": pid}
        await eventually(lambda: _row_is("mig-3", "mover", ("running", "robot")), what="rolled back")
        instance = await instance_of("mig-3", "mover")
        assert (instance.status, instance.desired) == ("failed", "stopped")
        assert "/nonexistent/mover-binary" in instance.message
        failed = await sync_to_async(list)(LogEvent.objects.filter(robot_id="mig-3", kind="cloud_component_failed"))
        assert len(failed) == 1 and failed[0].level == "error"
        assert await copies_of(stack, "mig-3", "mover") == []


async def test_volume_changes_travel_robot_to_cloud_and_back_in_changed_chunks_only(stack, tmp_path):
    config = skill(
        volumes=["data"],
        keeper=component("robot", name="Keeper"),
        mirror=component("cloud", name="Mirror", cloud={"command": ["sh", "-c", MIRROR]}),
    )
    token, _ = await make_robot("vol-1", skill=config)
    controller = RobotController(agent_settings(stack.server, "vol-1", token, tmp_path / "agent"), plugins={})
    async with configured(controller):
        await controller.start_skill(parse_skill_config(config))
        robot_volume = Path(controller.runtime.volumes_dir(SKILL)) / "data"
        cloud_volume = stack.volumes / "vol-1" / SKILL / "data"
        await eventually(lambda: _instance_running("vol-1", "mirror"), what="the cloud copy running")

        await asyncio.to_thread((robot_volume / "from-robot.txt").write_text, "hello from the robot\n")
        # The cloud copy read it (it copies it to a file of its own), and that file came back to the robot.
        seen = await eventually(
            lambda: _read(robot_volume / "seen-by-cloud.txt"), timeout=30, what="the cloud copy's file on the robot"
        )
        assert seen == "hello from the robot\n"
        assert (await asyncio.to_thread((cloud_volume / "from-robot.txt").read_text)) == seen

        big = os.urandom(8 * 128 * 1024)  # eight chunks
        await asyncio.to_thread(_write_atomically, robot_volume / "big.bin", big)
        await eventually(lambda: _holds(cloud_volume / "big.bin", big), timeout=30, what="big.bin in the cloud")
        sent = controller.volumes.chunks_sent
        changed = bytearray(big)
        changed[600 * 1024] ^= 0xFF  # one byte, in the fifth chunk
        # Written aside and renamed in, so no scan sees it half-written.
        await asyncio.to_thread(_write_atomically, robot_volume / "big.bin", bytes(changed))
        await eventually(lambda: _holds(cloud_volume / "big.bin", bytes(changed)), timeout=30, what="the change")
        assert controller.volumes.chunks_sent - sent == 1

        await asyncio.to_thread((robot_volume / "from-robot.txt").unlink)
        await eventually(lambda: not (cloud_volume / "from-robot.txt").exists(), timeout=30, what="the deletion")
        await controller.stop_skill(SKILL)


async def _instance_running(robot_id: str, name: str) -> bool:
    instance = await instance_of(robot_id, name)
    return instance is not None and instance.status == "running"


async def _holds(path: Path, content: bytes) -> bool:
    return await _read(path, binary=True) == content


async def _read(path: Path, *, binary: bool = False) -> str | bytes | None:
    try:
        return await asyncio.to_thread(path.read_bytes if binary else path.read_text)
    except FileNotFoundError:
        return None


def _write_atomically(path: Path, data: bytes) -> None:
    temp = path.with_name(".bridgeos-sync-test")
    temp.write_bytes(data)
    os.replace(temp, path)
