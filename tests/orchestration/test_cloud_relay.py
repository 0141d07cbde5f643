"""Cloud-side routing run by the cloud: the worker's relay per robot Skill, and the robot told where it is.

Real parts throughout: daphne and a Celery worker of a test cloud of their own (process runtime),
a robot authenticating over a real socket with its ROS master (a private rosmaster), the relay
process the worker starts, a Skill Router linked to it with what the login answered, and rospy
talker and listener nodes whose bytes are counted by the nodes themselves.
"""

from __future__ import annotations

import asyncio
import io
import os
import signal
import time
from collections.abc import Iterator

import httpx
import psutil
import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent import protocol
from bridgeos_agent.controller import RobotController
from bridgeos_agent.protocol import Event
from bridgeos_agent.router import RouterSettings, SkillRouter
from bridgeos_agent.router.cloudlink import CloudLink
from bridgeos_agent.skillconfig import parse_skill_config
from skills.cloud.relay import KIND_CLOUD_RELAY, observe_relays
from skills.models import CloudRelay, Component
from tests.agent.conftest import agent_settings, configured, make_robot
from tests.agent.test_router_cloudrelay import CONFIG, SKILL, ns, subscribers_of
from tests.cloud.wsutil import robot_login
from tests.conftest import eventually

from .conftest import make_stack

pytestmark = [
    pytest.mark.ros,
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(90),
    pytest.mark.usefixtures("robots_disconnect_before_flush"),
]


@pytest.fixture(scope="module")
def stack(django_db_setup, django_db_blocker, tmp_path_factory) -> Iterator:
    yield from make_stack("process", tmp_path_factory.mktemp("relay"))


@sync_to_async
def relay_row(robot_id: str) -> CloudRelay | None:
    return CloudRelay.objects.filter(skill__robot_id=robot_id).first()


async def relay_status(robot_id: str) -> str | None:
    row = await relay_row(robot_id)
    return row.status if row else None


async def relays_of(robot_id: str) -> list:
    return [o for o in await asyncio.to_thread(observe_relays) if o.robot == robot_id]


async def _is(value, expected) -> bool:
    return (await value) == expected


async def answers(url: str, token: str | None) -> int:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    async with httpx.AsyncClient(timeout=5) as http:
        return (await http.get(url + "/statistics", headers=headers)).status_code


async def test_the_worker_runs_a_skills_relay_the_robot_is_told_of_and_stops_it_with_the_skill(
    stack, rosmaster, nodes, tmp_path
):
    token, api_token = await make_robot("rl-one", skill=CONFIG)
    plain_token, plain_api_token = await make_robot("rl-plain", skill={**CONFIG, "components": _robot_only()})
    link, success = await robot_login(stack, "rl-one", token, ros_master=rosmaster)
    try:
        # The login answer names the Skill's relay (a valid protocol payload, parsed as the agent parses it).
        started = time.monotonic()
        parsed = protocol.AuthenticationSuccess.model_validate(success)
        assert parsed.cloud_relays is not None and set(parsed.cloud_relays) == {SKILL}
        relay = parsed.cloud_relays[SKILL]
        assert relay.url.startswith("http://127.0.0.1:") and len(relay.token) >= 32
        await eventually(lambda: _is(relay_status("rl-one"), "running"), timeout=45, what="the relay running")
        print(f"relay running {time.monotonic() - started:.1f} s after the login answer")
        [process] = await relays_of("rl-one")
        rss_mb = psutil.Process(process.id).memory_info().rss / 2**20
        print(f"cloud relay RSS: {rss_mb:.1f} MB")
        assert rss_mb < 200
        assert process.kind == KIND_CLOUD_RELAY and process.skill == SKILL
        # The token is in no column and not on the relay's command line (which any user can read).
        row = await relay_row("rl-one")
        assert relay.token not in repr(row.__dict__)
        assert relay.token not in " ".join(psutil.Process(process.id).cmdline())

        # Its control API answers the token only.
        assert await answers(relay.url, relay.token) == 200
        assert await answers(relay.url, None) == 401
        assert await answers(relay.url, relay.token[:-1] + "x") == 401

        # A router linked with what the login answered hands the cloud→cloud pair to the relay.
        cloud_link = CloudLink(relay.url, relay.token, poll=0.3)
        settings = RouterSettings(http_host="127.0.0.1", statistics_period=0.5, drain_timeout=5)
        router = SkillRouter(parse_skill_config(CONFIG), ros_master=rosmaster, settings=settings, robot="rl-one")
        router.cloud_link = cloud_link
        router.set_active("talker", "cloud")
        router.set_active("listener", "cloud")
        await router.start()
        try:
            assert cloud_link.up
            nodes.run("listener", "listener", namespace=ns("listener", "cloud"))
            assert await router.wait_ready("listener", "cloud", 30)
            count = 200
            talker_args = ("--tag", "c", "--rate", "200", "--count", str(count), "--size", "1000", "--wait")
            nodes.run("talker", "talker", *talker_args, namespace=ns("talker", "cloud"))
            await eventually(lambda: len(nodes.messages("listener")) >= count, what="every message via the relay")
            assert nodes.messages("listener") == [("c", seq) for seq in range(1, count + 1)]
            assert cloud_link.owned == {("/chatter", "listener")}
            [subscriber] = subscribers_of(rosmaster, f"{ns('talker', 'cloud')}/chatter")
            assert "cloudrelay" in subscriber and subscriber != router.node.name
        finally:
            await router.close()

        # A robot whose Skill runs only on the robot gets no relay.
        plain_link, plain = await robot_login(stack, "rl-plain", plain_token, ros_master=rosmaster)
        await plain_link.close()
        assert "cloud_relays" not in plain and await relay_row("rl-plain") is None

        # Killed, it is started again by the reconciler, on the same port with the same token.
        os.killpg(process.id, signal.SIGKILL)
        await eventually(lambda: _count(relays_of("rl-one"), 0), timeout=10, what="the relay gone")
        await asyncio.to_thread(stack.reconcile)
        await eventually(lambda: _count(relays_of("rl-one"), 1), timeout=20, what="the relay restarted")
        [again] = await relays_of("rl-one")
        assert again.id != process.id
        await eventually(lambda: _answered(relay.url, relay.token), timeout=20, what="the restarted relay answering")
        assert await answers(relay.url, None) == 401

        # Removed with its Skill (by its owner only).
        async with httpx.AsyncClient(base_url=stack.url, timeout=30) as api:
            remove = "/api/robot/rl-one/skill/remove"
            stranger = {"Authorization": f"Token {plain_api_token}"}
            assert (await api.post(remove, json={"skill": SKILL}, headers=stranger)).status_code == 404
            assert await relay_row("rl-one") is not None
            owner = {"Authorization": f"Token {api_token}"}
            assert (await api.post(remove, json={"skill": SKILL}, headers=owner)).status_code == 204
        await eventually(lambda: _count(relays_of("rl-one"), 0), timeout=30, what="the relay stopped")
        with pytest.raises(httpx.ConnectError):
            await answers(relay.url, relay.token)
    finally:
        await link.close()


async def test_a_skill_added_while_its_robot_is_connected_gets_its_relay_with_skill_start(stack, rosmaster):
    token, api_token = await make_robot("rl-late", skill={**CONFIG, "components": _robot_only()})
    link, success = await robot_login(stack, "rl-late", token, ros_master=rosmaster)
    try:
        assert "cloud_relays" not in success
        owner = {"Authorization": f"Token {api_token}"}
        async with httpx.AsyncClient(base_url=stack.url, timeout=30) as api:
            late = {**CONFIG, "skill_id": "late-relay", "skill": "Late relay"}
            added = await api.post("/api/robot/rl-late/skill/add", json={"config": late}, headers=owner)
            assert added.status_code == 201, added.text
            start = asyncio.create_task(
                api.post("/api/robot/rl-late/skill/late-relay/start", params={"wait": 10}, headers=owner)
            )
            frame = await link.next(Event.SKILL_START, timeout=20)
            await link.send(Event.ACK, reply_to=frame.id)
            assert (await start).status_code == 200
        order = protocol.SkillStart.model_validate(frame.data)
        assert order.skill == "late-relay" and order.cloud_relay is not None
        relay = order.cloud_relay
        await eventually(lambda: _answered(relay.url, relay.token), timeout=45, what="the late Skill's relay answering")
        assert await answers(relay.url, None) == 401
        # The robot-only Skill still has none.
        assert [o.skill for o in await relays_of("rl-late")] == ["late-relay"]
    finally:
        await link.close()


async def _answered(url: str, token: str) -> bool:
    try:
        return await answers(url, token) == 200
    except httpx.ConnectError:
        return False


async def _count(found, expected: int) -> bool:
    return len(await found) == expected


def _robot_only() -> dict:
    return {name: {**spec, "location": "robot"} for name, spec in CONFIG["components"].items()}


async def test_an_agent_links_its_skill_router_to_the_relay_the_cloud_named(stack, rosmaster, tmp_path):
    token, _ = await make_robot("rl-agent", skill=CONFIG)
    settings = agent_settings(stack.server, "rl-agent", token, tmp_path / "agent", detect_ros_master=False)
    controller = RobotController(settings)
    controller.local_ros_master = controller.ros_master = rosmaster
    async with configured(controller):
        relay = controller.cloud_relays[SKILL]
        await eventually(lambda: _is(relay_status("rl-agent"), "running"), timeout=45, what="the relay running")
        record = await controller.start_skill(parse_skill_config(CONFIG), starting=[])
        router = record.supervisor.context["router"]
        assert router.cloud_link is not None and router.cloud_link.url == relay.url
        await eventually(lambda: router.cloud_link.up, timeout=20, what="the router linked to the relay")


async def test_a_relay_goes_with_its_robot_and_with_cloud_down(stack, rosmaster):
    from django.core.management import call_command

    from robots.models import Robot

    for robot_id in ("rl-gone", "rl-moved", "rl-down"):
        token, _ = await make_robot(robot_id, skill=CONFIG)
        link, _ = await robot_login(stack, robot_id, token, ros_master=rosmaster)
        await link.close()
        await eventually(lambda r=robot_id: _is(relay_status(r), "running"), timeout=45, what=f"{robot_id}'s relay")

    # A deleted robot's relay: the reconciler removes what no row wants any more.
    await eventually(lambda: _disconnected("rl-gone"), timeout=30, what="the robot gone")
    await sync_to_async(lambda: Robot.objects.filter(id="rl-gone").delete())()
    await asyncio.to_thread(stack.reconcile)
    await eventually(lambda: _count(relays_of("rl-gone"), 0), timeout=30, what="the deleted robot's relay gone")
    assert len(await relays_of("rl-down")) == 1

    # A Skill left with no component allowed in the cloud: the reconciler stops its relay.
    await sync_to_async(lambda: Component.objects.filter(skill__robot_id="rl-moved").update(location="robot"))()
    await asyncio.to_thread(stack.reconcile)
    await eventually(lambda: _count(relays_of("rl-moved"), 0), timeout=30, what="the unwanted relay stopped")
    await eventually(lambda: _is(relay_status("rl-moved"), "stopped"), timeout=10, what="its row stopped")
    assert len(await relays_of("rl-down")) == 1

    # cloud_down stops every relay and says so in the rows.
    await sync_to_async(call_command)("cloud_down", stdout=io.StringIO())
    assert await relays_of("rl-down") == []
    assert await relay_status("rl-down") == "stopped"


@sync_to_async
def _disconnected(robot_id: str) -> bool:
    from robots.models import Robot

    return not Robot.objects.filter(id=robot_id, connected=True).exists()


async def test_a_relay_running_an_older_config_of_its_skill_is_replaced_at_the_next_login(stack, rosmaster):
    token, _ = await make_robot("rl-conf", skill=CONFIG)
    link, first = await robot_login(stack, "rl-conf", token, ros_master=rosmaster)
    await link.close()
    await eventually(lambda: _is(relay_status("rl-conf"), "running"), timeout=45, what="the relay running")
    [before] = await relays_of("rl-conf")
    # Same config at the next login: the same process.
    await eventually(lambda: _disconnected("rl-conf"), timeout=30, what="the robot gone")
    link, again = await robot_login(stack, "rl-conf", token, ros_master=rosmaster)
    await link.close()
    assert again["cloud_relays"] == first["cloud_relays"]
    await asyncio.sleep(2)
    assert [item.id for item in await relays_of("rl-conf")] == [before.id]
    # A changed config: a new process routing it, on the same port with the same token.
    changed = {**CONFIG, "skill": "Chat, renamed"}
    await sync_to_async(_set_config)("rl-conf", changed)
    await eventually(lambda: _disconnected("rl-conf"), timeout=30, what="the robot gone")
    link, third = await robot_login(stack, "rl-conf", token, ros_master=rosmaster)
    await link.close()
    assert third["cloud_relays"] == first["cloud_relays"]
    await eventually(lambda: _replaced(before.id), timeout=30, what="the relay replaced")
    relay = first["cloud_relays"][SKILL]
    await eventually(lambda: _answered(relay["url"], relay["token"]), timeout=20, what="the new relay answering")


def _set_config(robot_id: str, config: dict) -> None:
    from skills.models import Skill

    skill = Skill.objects.get(robot_id=robot_id, skill_id=SKILL)
    skill.config = config
    skill.save()


async def _replaced(pid: int) -> bool:
    found = await relays_of("rl-conf")
    return len(found) == 1 and found[0].id != pid
