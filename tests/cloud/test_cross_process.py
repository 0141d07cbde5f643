"""Two daphne processes sharing PostgreSQL and Redis behave like one cloud (issue 23, item 3).

The session's daphne is process A; each test starts process B beside it. Robots, clients and
REST calls are spread over both, so every path here crosses from one process to the other.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
import time

import httpx
import psycopg
import pytest
from asgiref.sync import sync_to_async
from django.conf import settings
from django.test import override_settings

from bridgeos_agent.protocol import Event
from monitoring.models import Event as LogEvent
from monitoring.models import Metric
from monitoring.sinks import conninfo_from_settings
from robots.models import Robot
from robots.presence import DEAD_PROCESS_REASON
from robots.tasks import sweep_dead_processes

from ..conftest import another_daphne
from .wsutil import client_link, make_owner, make_robot, robot_link

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio]

SKILL = "people-detection"


@pytest.fixture(scope="module")
def process_b(daphne_server, tmp_path_factory):
    """Start a second daphne of the same cloud beside the session's one, for this module's tests."""
    log = tmp_path_factory.mktemp("process-b") / "daphne.log"
    with another_daphne(log, BRIDGEOS_ROBOT_FRAMES_PER_S="2000") as (server, _):
        yield server


@sync_to_async
def count(model, **filters) -> int:
    return model.objects.filter(**filters).count()


@sync_to_async
def connected(robot_id: str) -> bool:
    return Robot.objects.get(id=robot_id).connected


def points(robot_id: str, start: int, count: int) -> list[dict]:
    return [{"name": "cpu", "value": i / 100, "ts": 1_700_000_000 + start + i, "skill": SKILL} for i in range(count)]


async def test_a_rest_command_reaches_a_robot_on_the_other_process_and_its_reply_returns(daphne_server, process_b):
    owner, api_token = await make_owner("owner")
    robot = await robot_link(process_b, "bot-b", await make_robot("bot-b", owner))
    headers = {"Authorization": f"Token {api_token}"}
    async with httpx.AsyncClient(base_url=daphne_server.url, headers=headers) as http:
        accepted = await http.post("/api/robot/bot-b/start", params={"wait": "5"})
        assert (await robot.next(Event.ROBOT_START)).event == Event.ROBOT_START
        assert accepted.status_code == 200, accepted.text
        assert accepted.json()["accepted"] and accepted.json()["reply"]["event"] == Event.ACK

        # The robot's refusal travels back across the processes too.
        robot.auto_ack = False
        pending = asyncio.ensure_future(http.post("/api/robot/bot-b/stop", params={"wait": "5"}))
        command = await robot.next(Event.ROBOT_STOP)
        await robot.send(Event.ERROR_MESSAGE, {"message": "busy", "code": "unavailable"}, reply_to=command.id)
        refused = await pending
    assert refused.status_code == 200, refused.text
    assert refused.json()["accepted"] is False
    assert refused.json()["reply"]["data"]["message"] == "busy"

    # The same through an app's WebSocket on A: the robot's answer is the answer to the app's frame.
    robot.auto_ack = True
    client = await client_link(daphne_server, api_token)
    pending = asyncio.ensure_future(client.request(Event.SKILL_START, {"robot": "bot-b", "skill": SKILL}))
    assert (await robot.next(Event.SKILL_START)).data == {"skill": SKILL}
    assert (await pending).event == Event.ACK
    await client.close()
    await robot.close()


async def test_a_client_on_one_process_sees_live_frames_of_robots_on_the_other(daphne_server, process_b):
    owner, api_token = await make_owner("owner")
    client = await client_link(daphne_server, api_token)
    robot = await robot_link(process_b, "bot-b", await make_robot("bot-b", owner))
    assert (await client.next(Event.CONNECTION_ESTABLISHED)).data["robot"] == "bot-b"

    await robot.send(Event.METRICS, {"metrics": points("bot-b", 0, 3)})
    await robot.send(Event.SKILL_STATUS, {"skill": SKILL, "status": "running"})
    seen: dict[str, dict] = {}
    while len(seen) < 2:
        frame = await client.next(Event.METRICS, Event.SKILL_STATUS)
        seen[frame.event] = frame.data
    # The live feed carries each series' latest value.
    assert seen[Event.METRICS]["robot"] == "bot-b"
    assert [(point["name"], point["value"]) for point in seen[Event.METRICS]["metrics"]] == [("cpu", 0.02)]
    assert (seen[Event.SKILL_STATUS]["robot"], seen[Event.SKILL_STATUS]["status"]) == ("bot-b", "running")
    await robot.close()
    assert (await client.next(Event.CONNECTION_LOST)).data["robot"] == "bot-b"
    await client.close()


async def test_frames_replayed_on_the_other_process_are_applied_once(daphne_server, process_b):
    owner, _ = await make_owner("owner")
    token = await make_robot("bot", owner)
    first = await robot_link(daphne_server, "bot", token)
    metrics = await first.send(Event.METRICS, {"metrics": points("bot", 0, 50)})
    status = await first.send(Event.COMPONENT_STATUS, {"skill": SKILL, "component": "detector", "status": "failed"})
    await first.wait_acked(metrics)
    await first.wait_acked(status)
    # The robot's link went half-open (the first process has not noticed yet) and the robot comes
    # back through the other process (a load balancer's choice), resending what it sent last: its
    # acks may have been lost on the way.
    second = await robot_link(process_b, "bot", token)
    for frame in (metrics, status):
        second.acked.setdefault(frame.id, asyncio.Event()).clear()
        await second.send_envelope(frame)
        await second.wait_acked(frame)
    assert await count(Metric, robot_id="bot") == 50
    assert await count(LogEvent, robot_id="bot", kind="component_status") == 1

    # And back to the first process, which already saw these ids itself.
    await first.close()
    await second.close()
    third = await robot_link(daphne_server, "bot", token)
    third.acked.setdefault(metrics.id, asyncio.Event()).clear()
    await third.send_envelope(metrics)
    await third.wait_acked(metrics)
    assert await count(Metric, robot_id="bot") == 50
    await third.close()


@contextlib.asynccontextmanager
async def metric_writes_blocked():
    """Hold a lock that makes every server process's COPY into the metric table wait until released."""
    connection = await psycopg.AsyncConnection.connect(conninfo_from_settings())
    try:
        async with connection.transaction():
            await connection.execute("LOCK TABLE monitoring_metric IN EXCLUSIVE MODE")
            yield
    finally:
        await connection.close()


async def test_a_frame_still_being_written_by_one_process_is_not_written_again_by_the_other(daphne_server, process_b):
    owner, _ = await make_owner("owner")
    token = await make_robot("bot", owner)
    first = await robot_link(daphne_server, "bot", token)
    async with metric_writes_blocked():
        metrics = await first.send(Event.METRICS, {"metrics": points("bot", 0, 50)})
        await asyncio.sleep(0.3)
        # The robot gives up on the first process while its write waits, and resends through the other.
        second = asyncio.ensure_future(robot_link(process_b, "bot", token))
        await asyncio.sleep(0.5)
    second_link = await second
    second_link.acked.setdefault(metrics.id, asyncio.Event()).clear()
    await second_link.send_envelope(metrics)
    await second_link.wait_acked(metrics)
    await asyncio.sleep(0.3)
    assert await count(Metric, robot_id="bot") == 50
    await first.close()
    await second_link.close()


async def test_robot_of_a_killed_process_resends_through_the_other_and_every_point_is_stored_once(
    daphne_server, tmp_path
):
    owner, _ = await make_owner("owner")
    token = await make_robot("streamer", owner)
    sent = []
    with another_daphne(tmp_path / "doomed.log", BRIDGEOS_PROCESS_TTL_S="2") as (doomed, process):
        link = await robot_link(doomed, "streamer", token)

        async def stream() -> None:
            for i in range(1000):
                sent.append(await link.send(Event.METRICS, {"metrics": points("streamer", i * 10, 10)}))
                await asyncio.sleep(0.005)

        streaming = asyncio.ensure_future(stream())
        await asyncio.sleep(0.6)
        process.send_signal(signal.SIGKILL)
        streaming.cancel()
        process.wait(timeout=10)
    killed = time.monotonic()
    with contextlib.suppress(asyncio.CancelledError):
        await streaming
    await link.close()

    # The robot comes back through the live process and resends what was never acked (its outbox).
    again = await robot_link(daphne_server, "streamer", token)
    reconnect_s = time.monotonic() - killed
    unacked = [frame for frame in sent if not link.acked[frame.id].is_set()]
    for frame in unacked:
        await again.send_envelope(frame)
    for frame in unacked:
        await again.wait_acked(frame)

    stored = await sync_to_async(list)(Metric.objects.filter(robot_id="streamer").values_list("ts", flat=True))
    assert len(sent) > 20, "the robot streamed before its process died"
    assert len(stored) == len(set(stored)) == 10 * len(sent)
    assert await connected("streamer")
    assert reconnect_s < 3
    await again.close()


async def test_state_changed_through_one_process_is_read_at_once_through_the_other(daphne_server, process_b):
    owner, api_token = await make_owner("owner")
    robot = await robot_link(daphne_server, "bot", await make_robot("bot", owner))
    headers = {"Authorization": f"Token {api_token}"}
    async with (
        httpx.AsyncClient(base_url=daphne_server.url, headers=headers) as via_a,
        httpx.AsyncClient(base_url=process_b.url, headers=headers) as via_b,
    ):

        async def detector_status(http: httpx.AsyncClient) -> str:
            state = (await http.get("/api/robot/bot")).json()
            (skill,) = state["skills"]
            return next(c["status"] for c in skill["components"] if c["component_id"] == "detector")

        # Both processes cache the robot's state; each change goes through A, each read right after through B.
        for status in ("starting", "running", "failed", "stopped"):
            await detector_status(via_b)
            report = await robot.send(
                Event.COMPONENT_STATUS, {"skill": SKILL, "component": "detector", "status": status}
            )
            await robot.wait_acked(report)
            assert await detector_status(via_b) == status
        for name in ("first", "second"):
            assert (await via_a.patch("/api/robot/bot", json={"name": name})).status_code == 200
            assert (await via_b.get("/api/robot/bot")).json()["name"] == name
    await robot.close()


async def test_celery_beat_sweeps_the_robots_of_a_dead_process_when_no_process_is_left(daphne_server, tmp_path):
    assert settings.CELERY_BEAT_SCHEDULE["sweep-dead-processes"]["task"] == sweep_dead_processes.name
    owner, api_token = await make_owner("owner")
    token = await make_robot("stranded", owner)
    # A cloud of one daphne (its own id, so the session's daphne is not one of its processes to sweep it).
    lone_cloud = {"BRIDGEOS_CLOUD_ID": "lone-cloud", "BRIDGEOS_PROCESS_TTL_S": "2"}
    with another_daphne(tmp_path / "lone.log", **lone_cloud) as (lone, process):
        link = await robot_link(lone, "stranded", token)
        assert await connected("stranded")
        process.send_signal(signal.SIGKILL)
        process.wait(timeout=10)
    killed = time.monotonic()
    swept: list[str] = []
    with override_settings(BRIDGEOS={**settings.BRIDGEOS, "CLOUD_ID": "lone-cloud"}):
        async with asyncio.timeout(15):
            while not swept:
                # What beat queues every heartbeat, run as the worker runs it.
                swept = (await sync_to_async(sweep_dead_processes.apply)()).get()
                await asyncio.sleep(0.2)
    assert swept == ["stranded"]
    assert time.monotonic() - killed < 15
    assert not await connected("stranded")
    reasons = await sync_to_async(list)(
        LogEvent.objects.filter(robot_id="stranded", kind="connection_lost").values_list("data__reason", flat=True)
    )
    assert reasons == [DEAD_PROCESS_REASON]
    async with httpx.AsyncClient(base_url=daphne_server.url) as http:
        response = await http.post(
            "/api/robot/stranded/start", headers={"Authorization": f"Token {api_token}"}, params={"wait": "2"}
        )
    assert response.status_code == 409, response.text
    await link.close()
