"""The robot door /ws/robot/ over a real socket, with the real Redis layer and PostgreSQL."""

from __future__ import annotations

import asyncio
import json

import httpx
import pytest
import websockets
from asgiref.sync import sync_to_async

from bridgeos_agent import protocol
from bridgeos_agent.link import AuthenticationError, Link
from bridgeos_agent.protocol import Event
from monitoring.models import Event as LogEvent
from monitoring.models import Metric
from robots.models import Robot
from skills.models import Component, Skill
from tests.conftest import eventually

from .wsutil import make_owner, make_robot, new_robot_link, robot_link

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio]


@sync_to_async
def robot_row(robot_id: str) -> Robot:
    return Robot.objects.get(id=robot_id)


@sync_to_async
def component_row(robot_id: str, component_id: str) -> Component:
    return Component.objects.get(skill__robot_id=robot_id, component_id=component_id)


@sync_to_async
def count(model, **filters) -> int:
    return model.objects.filter(**filters).count()


async def test_robot_authenticates_and_receives_its_config(daphne_server):
    owner, _ = await make_owner("owner")
    token = await make_robot("r1", owner)
    link = Link(daphne_server.ws_url + "/ws/robot/")
    success = await link.connect(Event.AUTHENTICATION_ROBOT, {"robot": "r1", "token": token})
    assert success.data == {"robot": "r1"}
    assert (await link.next(Event.CONNECTION_ESTABLISHED)).data["robot"] == "r1"
    config = await link.next(Event.ROBOT_CONFIG)
    assert config.data["config"]["heuristic"] == "resource_usage"
    robot = await robot_row("r1")
    assert robot.connected and robot.last_seen is not None and robot.channel
    assert await count(LogEvent, robot_id="r1", kind="connection_established") == 1
    await link.close()
    robot = await eventually(lambda: _disconnected("r1"), timeout=5)
    assert await count(LogEvent, robot_id="r1", kind="connection_lost") == 1


@sync_to_async
def _disconnected(robot_id: str):
    robot = Robot.objects.get(id=robot_id)
    return robot if not robot.connected else None


@pytest.mark.parametrize(
    ("first_frame", "reason"),
    [
        ('{"event": "metrics", "id": "m1", "data": {"metrics": []}}', "first frame must be authentication_robot"),
        ("not json at all", "first frame must be authentication_robot"),
        ('{"event": "authentication_robot", "id": "a1", "data": {"robot": "r1", "token": "brt_wrong"}}', "wrong token"),
        ('{"event": "authentication_robot", "id": "a1", "data": {"robot": "ghost", "token": "x"}}', "unknown robot"),
        ('{"event": "authentication_robot", "id": "a1", "data": {"robot": "r1"}}', "data.token"),
    ],
)
async def test_anything_but_valid_credentials_first_is_refused_and_closed(daphne_server, first_frame, reason):
    owner, _ = await make_owner("owner")
    await make_robot("r1", owner, with_skill=False)
    async with websockets.connect(daphne_server.ws_url + "/ws/robot/") as ws:
        await ws.send(first_frame)
        answer = protocol.decode(await asyncio.wait_for(ws.recv(), 5))
        assert answer.event == Event.AUTHENTICATION_FAILURE
        assert reason in answer.data["reason"]
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await asyncio.wait_for(ws.recv(), 5)
        assert closed.value.rcvd.code == 4001
    assert not (await robot_row("r1")).connected


async def test_login_frames_are_resent_until_acked_and_never_after(daphne_server):
    owner, _ = await make_owner("owner")
    token = await make_robot("r1", owner, with_skill=False)
    async with websockets.connect(daphne_server.ws_url + "/ws/robot/") as ws:
        auth = {"robot": "r1", "token": token}
        await ws.send(protocol.encode(protocol.make(Event.AUTHENTICATION_ROBOT, auth, now=0.0)))
        first = [protocol.decode(await asyncio.wait_for(ws.recv(), 5)) for _ in range(3)]
        assert [frame.event for frame in first] == [
            Event.AUTHENTICATION_SUCCESS,
            Event.CONNECTION_ESTABLISHED,
            Event.ROBOT_CONFIG,
        ]
        # Not acked: both acked events come again, with their ids, about a second later (the resend's
        # timer was set inside the login's gathered send, and its writes once waited for another one).
        again = [protocol.decode(await asyncio.wait_for(ws.recv(), 5)) for _ in range(2)]
        # Each on its own jittered schedule, so in either order.
        assert sorted((frame.event, frame.id) for frame in again) == sorted(
            (frame.event, frame.id) for frame in first[1:]
        )
        for frame in again:
            await ws.send(protocol.ack_text(frame.id, now=0.0))
        # Acked: nothing more, though the next resend (about two seconds on) was due.
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(ws.recv(), 3.5)


async def test_link_raises_on_refused_credentials(daphne_server):
    owner, _ = await make_owner("owner")
    await make_robot("r1", owner, with_skill=False)
    with pytest.raises(AuthenticationError, match="wrong token"):
        await Link(daphne_server.ws_url + "/ws/robot/").connect(
            Event.AUTHENTICATION_ROBOT, {"robot": "r1", "token": "brt_nope"}
        )


async def test_robot_reports_are_applied_and_acknowledged(daphne_server):
    link, _ = await new_robot_link(daphne_server, "r1")
    reports = [
        (Event.SKILL_CONNECT, {"skill": "people-detection", "manager_url": "http://127.0.0.1:7000"}),
        (Event.SKILL_STATUS, {"skill": "people-detection", "status": "running"}),
        (
            Event.COMPONENT_STATUS,
            {"skill": "people-detection", "component": "sampler", "status": "running", "location": "robot"},
        ),
        (Event.COMPONENT_LOCATION, {"skill": "people-detection", "component": "sampler", "location": "cloud"}),
        (
            Event.COMPONENT_INFORMATION,
            {
                "skill": "people-detection",
                "component": "sampler",
                "location": "cloud",
                "container": {"id": "abc", "ip": "10.1.0.5"},
            },
        ),
        (Event.OFFLOADING, {"mode": "manual"}),
    ]
    for event, data in reports:
        envelope = await link.send(event, data)
        await link.wait_acked(envelope)
    skill = await sync_to_async(Skill.objects.get)(robot_id="r1", skill_id="people-detection")
    assert skill.status == "running"
    sampler = await component_row("r1", "sampler")
    assert sampler.status == "running"
    assert sampler.active_location == "cloud"
    assert sampler.container == {"cloud": {"id": "abc", "ip": "10.1.0.5"}}
    assert (await robot_row("r1")).config["offloading"] == "manual"
    assert await count(LogEvent, robot_id="r1", kind="skill_connect") == 1

    shutdown = await link.send(Event.SHUTDOWN, {"reason": "battery empty"})
    await link.wait_acked(shutdown)
    assert (await robot_row("r1")).status == "shutdown"
    await link.close()


async def test_a_failed_components_reason_is_kept_with_its_status_and_cleared_when_it_runs(daphne_server):
    link, api_token = await new_robot_link(daphne_server, "r1")
    why = "short of bandwidth and no running movable component frees enough; it must run on the robot"
    failed = {"skill": "people-detection", "component": "pointcloud", "status": "failed", "message": why}
    await link.wait_acked(await link.send(Event.COMPONENT_STATUS, failed))

    async def info() -> dict:
        async with httpx.AsyncClient(base_url=daphne_server.url, headers={"Authorization": f"Token {api_token}"}) as c:
            answer = await c.get("/api/robot/r1/info")
        assert answer.status_code == 200, answer.text
        (skill,) = answer.json()["skills"]
        return {c["component_id"]: c for c in skill["components"]}

    assert ((await info())["pointcloud"]["status"], (await info())["pointcloud"]["message"]) == ("failed", why)
    assert (await info())["sampler"]["message"] == ""
    running = {"skill": "people-detection", "component": "pointcloud", "status": "running", "location": "robot"}
    await link.wait_acked(await link.send(Event.COMPONENT_STATUS, running))
    assert ((await info())["pointcloud"]["status"], (await info())["pointcloud"]["message"]) == ("running", "")
    await link.close()


async def test_robot_sends_its_local_skill_config(daphne_server):
    link, _ = await new_robot_link(daphne_server, "r1", with_skill=False)
    config = {
        "skill": "Echo",
        "skill_id": "echo",
        "components": {"talker": {"name": "Talker", "location": "robot", "robot": {"command": ["echo", "hi"]}}},
    }
    envelope = await link.send(Event.SKILL_CONFIG, {"skill": "echo", "config": config})
    await link.wait_acked(envelope)
    assert await count(Component, skill__robot_id="r1", skill__skill_id="echo", component_id="talker") == 1

    answer = await link.request(Event.SKILL_CONFIG_GET, {"skill": "echo"})
    assert answer.event == Event.SKILL_CONFIG
    assert answer.data["config"]["components"]["talker"]["location"] == "robot"


async def test_robot_asks_for_config_and_statuses(daphne_server):
    link, _ = await new_robot_link(daphne_server, "r1")
    config = await link.request(Event.ROBOT_CONFIG_GET)
    assert config.event == Event.ROBOT_CONFIG
    assert config.data["config"]["offloading"] == "auto"
    status = await link.request(Event.COMPONENT_STATUS_GET, {"skill": "people-detection", "component": "detector"})
    assert status.event == Event.COMPONENT_STATUS
    assert status.data["status"] == "stopped"
    await link.close()


async def test_duplicate_event_is_applied_once(daphne_server):
    link, _ = await new_robot_link(daphne_server, "r1")
    data = {"skill": "people-detection", "component": "detector", "status": "failed"}
    first = await link.send(Event.COMPONENT_STATUS, data)
    await link.wait_acked(first)
    # The same frame again (a retransmission whose ack was lost): acked, not applied again.
    link.acked[first.id].clear()
    await link.send_envelope(first)
    await link.wait_acked(first)
    assert await count(LogEvent, robot_id="r1", kind="component_status") == 1
    await link.close()


async def test_duplicate_is_recognised_after_reconnecting(daphne_server):
    owner, _ = await make_owner("owner")
    token = await make_robot("r1", owner)
    link = await robot_link(daphne_server, "r1", token)
    first = await link.send(Event.SKILL_STATUS, {"skill": "people-detection", "status": "starting"})
    await link.wait_acked(first)
    await link.close()
    await eventually(lambda: _disconnected("r1"), timeout=5)

    # A new connection (a new consumer) still knows the id was applied.
    again = await robot_link(daphne_server, "r1", token)
    await again.send_envelope(first)
    await again.wait_acked(first)
    assert await count(LogEvent, robot_id="r1", kind="skill_status") == 1
    await again.close()


async def test_metrics_are_stored_then_acknowledged(daphne_server):
    link, _ = await new_robot_link(daphne_server, "r1")
    points = [
        {"name": "cpu", "value": i / 10, "ts": 1_700_000_000 + i, "skill": "people-detection", "component": "sampler"}
        for i in range(100)
    ]
    envelope = await link.send(Event.METRICS, {"metrics": points})
    await link.wait_acked(envelope)
    # The ack comes only after the rows are committed.
    assert await count(Metric, robot_id="r1", name="cpu", component="sampler") == 100
    await link.send_envelope(envelope)
    await asyncio.sleep(0.5)
    assert await count(Metric, robot_id="r1") == 100
    await link.close()


@pytest.mark.parametrize(
    ("frame", "code", "field"),
    [
        ("{not json", "invalid_json", None),
        ('["a", "list"]', "not_object", None),
        ('{"event": "fly", "id": "x1", "data": {}}', "unknown_event", "event"),
        ('{"event": "skill_connnect", "id": "x1", "data": {"skill": "a"}}', "unknown_event", "event"),
        ('{"event": "robot_start", "id": "x1", "data": {}}', "forbidden_event", "event"),
        (
            '{"event": "skill_status", "id": "x1", "data": {"skill": "people-detection", "status": "dancing"}}',
            "invalid_payload",
            "data.status",
        ),
        (
            '{"event": "metrics", "id": "x1", "data": {"metrics": [{"name": "cpu", "value": "high", "ts": 1}]}}',
            "invalid_payload",
            "data.metrics.0.value",
        ),
        (
            '{"event": "skill_status", "id": "x1", "data": {"skill": "people-detection", "status": "running", "extra": 1}}',
            "invalid_payload",
            "data.extra",
        ),
        (
            '{"event": "skill_status", "id": "x1", "data": {"robot": "r2", "skill": "people-detection", "status": "running"}}',
            "forbidden",
            "data.robot",
        ),
        (
            '{"event": "skill_status", "id": "x1", "data": {"skill": "not-mine", "status": "running"}}',
            "not_found",
            "data.skill",
        ),
        (
            '{"event": "component_location", "id": "x1", "data": {"skill": "people-detection", "component": "pointcloud", "location": "cloud"}}',
            "not_found",
            "data.location",
        ),
    ],
)
async def test_bad_frames_get_a_clear_error_and_change_nothing(daphne_server, frame, code, field):
    owner, _ = await make_owner("owner")
    other, _ = await make_owner("other")
    await make_robot("r2", other)
    link = await robot_link(daphne_server, "r1", await make_robot("r1", owner))
    events_before = await count(LogEvent)
    await link.ws.send(frame)
    error = await link.next(Event.ERROR_MESSAGE)
    assert error.data["code"] == code
    assert error.data.get("field") == field
    assert "Traceback" not in error.data["message"]
    # Nothing changed, and the connection is still usable.
    assert await count(LogEvent) == events_before
    assert await count(Skill, status="running") == 0
    assert (await component_row("r1", "pointcloud")).active_location == ""
    envelope = await link.send(Event.SKILL_STATUS, {"skill": "people-detection", "status": "running"})
    await link.wait_acked(envelope)
    await link.close()


async def test_oversized_frame_is_refused(daphne_server):
    link, _ = await new_robot_link(daphne_server, "r1")
    padding = "x" * (1024 * 1024)
    await link.ws.send(json.dumps({"event": "error_message", "id": "big", "data": {"message": padding}}))
    error = await link.next(Event.ERROR_MESSAGE)
    assert error.data["code"] == "too_large"
    await link.close()


async def test_a_flood_is_refused_then_closed(daphne_server):
    link, _ = await new_robot_link(daphne_server, "r1")
    # Acks cost the cloud almost nothing, so they arrive faster than the limit refills.
    frame = protocol.encode(protocol.ack_frame("nothing-pending", now=0))
    # Far more than the limit (2,000 frames/s in tests) admits, however fast the server drains them.
    for _ in range(20_000):
        await link.ws.send(frame)
    error = await link.next(Event.ERROR_MESSAGE, timeout=20)
    while error.data["code"] != "rate_limited":
        error = await link.next(Event.ERROR_MESSAGE, timeout=20)
    await asyncio.wait_for(link.closed.wait(), 20)
    assert link.close_code == 4008


async def test_a_newer_connection_replaces_the_old_one(daphne_server):
    owner, _ = await make_owner("owner")
    token = await make_robot("r1", owner)
    old = await robot_link(daphne_server, "r1", token)
    new = await robot_link(daphne_server, "r1", token)
    await asyncio.wait_for(old.closed.wait(), 5)
    assert old.close_code == 4009
    # The old connection closing does not mark the robot offline: the new one holds it.
    await asyncio.sleep(0.3)
    assert (await robot_row("r1")).connected
    await new.close()
