"""The client door /ws/client/: live feed scoped to the user's robots, and commands relayed to robots."""

from __future__ import annotations

import asyncio
import re
import time

import httpx
import pytest
import websockets
from asgiref.sync import sync_to_async

from bridgeos_agent import protocol
from bridgeos_agent.link import AuthenticationError, Link
from bridgeos_agent.protocol import Event
from robots.models import Robot
from robots.services import RobotOffline, relay_command

from .wsutil import client_link, make_owner, make_robot, new_robot_link, robot_link

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio]


async def collect(link: Link, seconds: float) -> list:
    """Gather every frame a link receives for a while."""
    frames = []
    deadline = time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        try:
            frames.append(await link.next(timeout=left))
        except TimeoutError:
            break
    return frames


async def collect_until(link: Link, wanted: set[tuple[str, str]], timeout: float = 15.0, linger: float = 1.0) -> list:
    """Gather frames until every wanted (event, robot) has come, and for ``linger`` seconds more."""
    frames: list = []
    deadline = time.monotonic() + timeout
    while not wanted <= {(frame.event, frame.data.get("robot")) for frame in frames}:
        if (left := deadline - time.monotonic()) <= 0:
            break
        try:
            frames.append(await link.next(timeout=left))
        except TimeoutError:
            break
    return frames + await collect(link, linger)


async def test_client_authenticates_with_an_api_token(daphne_server):
    _, token = await make_owner("alice")
    link = Link(daphne_server.ws_url + "/ws/client/")
    success = await link.connect(Event.AUTHENTICATION_CLIENT, {"token": token})
    assert success.data == {"user": "alice"}
    await link.close()


async def test_a_wrong_token_is_refused_and_closed(daphne_server):
    with pytest.raises(AuthenticationError, match="invalid token"):
        await Link(daphne_server.ws_url + "/ws/client/").connect(Event.AUTHENTICATION_CLIENT, {"token": "nope"})
    async with websockets.connect(daphne_server.ws_url + "/ws/client/") as ws:
        await ws.send('{"event": "robot_start", "id": "x", "data": {"robot": "r1"}}')
        answer = protocol.decode(await ws.recv())
        assert answer.event == Event.AUTHENTICATION_FAILURE
        with pytest.raises(websockets.ConnectionClosed) as closed:
            await ws.recv()
        assert closed.value.rcvd.code == 4001


async def test_client_authenticates_with_the_dashboard_session(daphne_server):
    await make_owner("alice")
    async with httpx.AsyncClient(base_url=daphne_server.url) as http:
        form = await http.get("/accounts/login/")
        csrf = re.search(r'name="csrfmiddlewaretoken" value="([^"]+)"', form.text).group(1)
        await http.post(
            "/accounts/login/",
            data={"csrfmiddlewaretoken": csrf, "username": "alice", "password": "alice-pass-123"},
            headers={"Referer": daphne_server.url + "/accounts/login/"},
        )
        cookie = f"sessionid={http.cookies['sessionid']}"
    link = Link(daphne_server.ws_url + "/ws/client/")
    success = await link.connect(Event.AUTHENTICATION_CLIENT, {}, headers={"Cookie": cookie})
    assert success.data["user"] == "alice"
    await link.close()


async def test_a_client_never_receives_another_users_robot(daphne_server):
    alice, alice_token = await make_owner("alice")
    bob, _ = await make_owner("bob")
    _, staff_token = await make_owner("ops", staff=True)
    alice_client = await client_link(daphne_server, alice_token)
    staff_client = await client_link(daphne_server, staff_token)
    robot_a = await robot_link(daphne_server, "alice-bot", await make_robot("alice-bot", alice))
    robot_b = await robot_link(daphne_server, "bob-bot", await make_robot("bob-bot", bob))
    for robot in (robot_a, robot_b):
        await robot.send(Event.METRICS, {"metrics": [{"name": "cpu", "value": 0.5, "ts": time.time()}]})
        await robot.send(Event.SKILL_STATUS, {"skill": "people-detection", "status": "running"})
    await robot_b.close()

    alices = {(Event.METRICS, "alice-bot"), (Event.SKILL_STATUS, "alice-bot")}
    bobs = {(Event.METRICS, "bob-bot"), (Event.SKILL_STATUS, "bob-bot"), (Event.CONNECTION_LOST, "bob-bot")}
    # Until the staff client has all of bob's frames, and a second more: alice would have had them by then.
    seen_by_staff = await collect_until(staff_client, bobs)
    seen_by_alice = await collect_until(alice_client, alices)
    robots_alice_saw = {frame.data.get("robot") for frame in seen_by_alice}
    assert "bob-bot" not in robots_alice_saw
    assert {(f.event, f.data.get("robot")) for f in seen_by_alice} >= alices
    assert {(f.event, f.data.get("robot")) for f in seen_by_staff} >= bobs
    # Nor can she ask about it: it is "not found", exactly like a robot that does not exist.
    answer = await alice_client.request(Event.SKILL_STATUS_GET, {"robot": "bob-bot", "skill": "people-detection"})
    assert answer.event == Event.ERROR_MESSAGE
    assert answer.data["code"] == "not_found"
    await robot_a.close()


async def test_connection_events_reach_the_owner_live(daphne_server):
    alice, token = await make_owner("alice")
    robot_token = await make_robot("alice-bot", alice)
    client = await client_link(daphne_server, token)
    robot = await robot_link(daphne_server, "alice-bot", robot_token)
    assert (await client.next(Event.CONNECTION_ESTABLISHED)).data["robot"] == "alice-bot"
    await robot.close()
    assert (await client.next(Event.CONNECTION_LOST)).data["robot"] == "alice-bot"


async def test_a_command_round_trips_client_cloud_robot_cloud_client(daphne_server):
    robot, token = await new_robot_link(daphne_server, "alice-bot", "alice")
    client = await client_link(daphne_server, token)

    pending = asyncio.ensure_future(
        client.request(Event.SKILL_START, {"robot": "alice-bot", "skill": "people-detection"})
    )
    command = await robot.next(Event.SKILL_START)
    assert command.data == {"skill": "people-detection"}
    answer = await pending
    # The robot's ack comes back to the client as the answer to the client's own frame.
    assert answer.event == Event.ACK, answer.data

    robot.auto_ack = False
    pending = asyncio.ensure_future(
        client.request(
            Event.COMPONENT_MIGRATE, {"robot": "alice-bot", "skill": "people-detection", "component": "sampler"}
        )
    )
    command = await robot.next(Event.COMPONENT_MIGRATE)
    await robot.send(
        Event.ERROR_MESSAGE, {"message": "no cloud to migrate to", "code": "unavailable"}, reply_to=command.id
    )
    answer = await pending
    assert answer.event == Event.ERROR_MESSAGE
    assert answer.data["message"] == "no cloud to migrate to"


async def test_a_command_to_an_offline_robot_fails_at_once(daphne_server):
    alice, token = await make_owner("alice")
    await make_robot("alice-bot", alice)
    client = await client_link(daphne_server, token)
    started = time.monotonic()
    answer = await client.request(Event.ROBOT_STOP, {"robot": "alice-bot"})
    assert answer.event == Event.ERROR_MESSAGE
    assert answer.data["code"] == "robot_offline"
    assert time.monotonic() - started < 1.0


async def test_client_requests_are_answered_from_the_cloud_records(daphne_server):
    robot, token = await new_robot_link(daphne_server, "alice-bot", "alice")
    sent = await robot.send(
        Event.METRICS, {"metrics": [{"name": "cpu", "value": v, "ts": 1000.0 + v} for v in range(5)]}
    )
    await robot.wait_acked(sent)
    client = await client_link(daphne_server, token)

    config = await client.request(Event.ROBOT_CONFIG_GET, {"robot": "alice-bot"})
    assert config.event == Event.ROBOT_CONFIG and config.data["config"]["offloading"] == "auto"
    mode = await client.request(Event.OFFLOADING_GET, {"robot": "alice-bot"})
    assert mode.event == Event.OFFLOADING and mode.data["mode"] == "auto"
    status = await client.request(Event.SKILL_STATUS_GET, {"robot": "alice-bot", "skill": "people-detection"})
    assert status.event == Event.SKILL_STATUS and status.data["status"] == "stopped"
    skill_config = await client.request(Event.SKILL_CONFIG_GET, {"robot": "alice-bot", "skill": "people-detection"})
    assert set(skill_config.data["config"]["components"]) == {"pointcloud", "sampler", "detector"}
    component = await client.request(
        Event.COMPONENT_STATUS_GET, {"robot": "alice-bot", "skill": "people-detection", "component": "detector"}
    )
    assert component.event == Event.COMPONENT_STATUS and component.data["status"] == "stopped"
    latest = await client.request(Event.METRICS_GET, {"robot": "alice-bot", "names": ["cpu"]})
    assert latest.event == Event.METRICS
    assert latest.data["metrics"] == [{"name": "cpu", "value": 4.0, "ts": 1004.0}]
    history = await client.request(Event.METRICS_GET, {"robot": "alice-bot", "since": 1002.0})
    assert [p["value"] for p in history.data["metrics"]] == [4.0, 3.0, 2.0]
    missing = await client.request(Event.SKILL_STATUS_GET, {"robot": "alice-bot", "skill": "nope"})
    assert missing.data == {
        "message": "robot alice-bot has no skill 'nope'",
        "code": "not_found",
        "field": "data.skill",
    }
    unnamed = await client.request(Event.ROBOT_CONFIG_GET, {})
    assert unnamed.data["field"] == "data.robot"
    await robot.close()


async def test_config_update_is_validated_stored_and_relayed(daphne_server):
    robot, token = await new_robot_link(daphne_server, "alice-bot", "alice")
    client = await client_link(daphne_server, token)

    answer = await client.request(Event.ROBOT_CONFIG_UPDATE, {"robot": "alice-bot", "changes": {"threshold": 0.9}})
    assert answer.event == Event.ACK
    update = await robot.next(Event.ROBOT_CONFIG_UPDATE)
    assert update.data == {"changes": {"threshold": 0.9}}
    stored = await sync_to_async(Robot.objects.get)(id="alice-bot")
    assert stored.config["threshold"] == 0.9

    bad = await client.request(Event.ROBOT_CONFIG_UPDATE, {"robot": "alice-bot", "changes": {"threshold": "high"}})
    assert bad.event == Event.ERROR_MESSAGE
    assert bad.data["field"] == "data.config"
    assert bad.data["message"].startswith("threshold:")
    stored = await sync_to_async(Robot.objects.get)(id="alice-bot")
    assert stored.config["threshold"] == 0.9

    # Stored while the robot is offline, and acknowledged: the robot gets it with its config on reconnect.
    await robot.close()
    await asyncio.sleep(0.3)
    offline = await client.request(Event.OFFLOADING, {"robot": "alice-bot", "mode": "cloud"})
    assert offline.event == Event.ACK
    stored = await sync_to_async(Robot.objects.get)(id="alice-bot")
    assert stored.config["offloading"] == "cloud"


async def test_relay_command_reaches_the_robot_and_returns_its_answer(daphne_server):
    robot, _ = await new_robot_link(daphne_server, "alice-bot", "alice")
    requests = [
        (Event.OFFLOADING_GET, {}, Event.OFFLOADING, {"mode": "auto"}),
        (
            Event.SKILL_STATUS_GET,
            {"skill": "people-detection"},
            Event.SKILL_STATUS,
            {"skill": "people-detection", "status": "running"},
        ),
        (Event.METRICS_GET, {"names": ["cpu"]}, Event.METRICS, {"metrics": [{"name": "cpu", "value": 0.3, "ts": 5.0}]}),
        (
            Event.SKILL_CONFIG_GET,
            {"skill": "people-detection"},
            Event.SKILL_CONFIG,
            {"skill": "people-detection", "config": {"skill": "x"}},
        ),
        (
            Event.COMPONENT_STATUS_GET,
            {"skill": "people-detection", "component": "sampler"},
            Event.COMPONENT_STATUS,
            {"skill": "people-detection", "component": "sampler", "status": "running"},
        ),
    ]
    for event, data, reply_event, reply_data in requests:
        pending = asyncio.ensure_future(relay_command("alice-bot", event, data, wait=5))
        request = await robot.next(event)
        assert request.data == data
        await robot.send(reply_event, reply_data, reply_to=request.id)
        reply = await pending
        assert reply.event == reply_event
        assert reply.data == reply_data
    await robot.close()
    await asyncio.sleep(0.3)
    with pytest.raises(RobotOffline):
        await relay_command("alice-bot", Event.ROBOT_START, {}, wait=1)


async def test_every_command_reaches_the_robot_and_its_ack_returns(daphne_server):
    robot, token = await new_robot_link(daphne_server, "alice-bot", "alice")
    client = await client_link(daphne_server, token)
    commands = [
        (Event.ROBOT_START, {}),
        (Event.ROBOT_STOP, {}),
        (Event.SKILL_START, {"skill": "people-detection"}),
        (Event.SKILL_STOP, {"skill": "people-detection"}),
        (Event.COMPONENT_START, {"skill": "people-detection", "component": "sampler", "location": "cloud"}),
        (Event.COMPONENT_STOP, {"skill": "people-detection", "component": "sampler", "location": "cloud"}),
        (Event.COMPONENT_MIGRATE, {"skill": "people-detection", "component": "sampler", "location": "robot"}),
        (Event.ROBOT_CONFIG_UPDATE, {"changes": {"heartbeat_interval": 2.0}}),
        (Event.OFFLOADING, {"mode": "robot"}),
        (Event.SHUTDOWN, {"reason": "maintenance"}),
    ]
    for event, data in commands:
        pending = asyncio.ensure_future(client.request(event, {"robot": "alice-bot", **data}))
        received = await robot.next(event)
        assert received.data == data
        answer = await pending
        assert answer.event == Event.ACK, (event, answer.data)
    await robot.close()


async def test_a_components_api_reply_goes_to_its_requester_and_nothing_else(daphne_server):
    robot, _ = await new_robot_link(daphne_server, "alice-bot", "alice")
    log_start = daphne_server.log.stat().st_size
    data = {"skill": "people-detection", "method": "GET", "path": "/components", "query": "", "body": None}
    pending = asyncio.ensure_future(relay_command("alice-bot", Event.COMPONENTS_API, data, wait=5))
    request = await robot.next(Event.COMPONENTS_API)
    answer = {"skill": "people-detection", "status": 200, "body": {"components": []}}
    await robot.send(Event.COMPONENTS_API_REPLY, answer, reply_to=request.id)
    reply = await pending
    assert (reply.event, reply.data) == (Event.COMPONENTS_API_REPLY, answer)
    # A late reply (its requester gone) is dropped too; neither is refused as an internal error.
    await robot.send(Event.COMPONENTS_API_REPLY, answer, reply_to="nobody-asked")
    probe = await robot.request(Event.SKILL_STATUS, {"skill": "people-detection", "status": "running"})
    assert probe.event == Event.ACK
    errors = [frame for frame in drain(robot) if frame.event == Event.ERROR_MESSAGE]
    assert errors == []
    with daphne_server.log.open() as log:
        log.seek(log_start)
        assert "Traceback" not in log.read()
    await robot.close()


async def test_a_client_subscribed_to_some_robots_is_sent_only_their_metrics(daphne_server):
    alice, token = await make_owner("alice")
    bob, _ = await make_owner("bob")
    robots = {
        rid: await robot_link(daphne_server, rid, await make_robot(rid, alice, with_skill=False))
        for rid in ("alice-1", "alice-2")
    }
    await make_robot("bob-bot", bob, with_skill=False)
    client = await client_link(daphne_server, token)

    async def metrics_from_both() -> set[str]:
        for robot in robots.values():
            await robot.send(Event.METRICS, {"metrics": [{"name": "cpu", "value": 0.5, "ts": time.time()}]})
        return {frame.data["robot"] for frame in await collect(client, 1.0) if frame.event == Event.METRICS}

    # Another user's robot and a missing one are refused alike, and the refusal changes nothing.
    for hidden in ("bob-bot", "no-such-bot"):
        refused = await client.request(Event.METRICS_SUBSCRIBE, {"robots": ["alice-1", hidden]})
        assert (refused.event, refused.data["code"], refused.data["field"]) == (
            Event.ERROR_MESSAGE,
            "not_found",
            "data.robots",
        )
    assert await metrics_from_both() == {"alice-1", "alice-2"}
    assert (await client.request(Event.METRICS_SUBSCRIBE, {"robots": ["alice-2"]})).event == Event.ACK
    assert await metrics_from_both() == {"alice-2"}
    assert (await client.request(Event.METRICS_SUBSCRIBE, {"robots": []})).event == Event.ACK
    assert await metrics_from_both() == set()
    for link in (*robots.values(), client):
        await link.close()


def drain(link) -> list:
    """Return every frame the link has received and not yet read."""
    frames = []
    while not link.inbox.empty():
        frames.append(link.inbox.get_nowait())
    return frames
