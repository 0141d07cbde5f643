"""Robot tokens rotated with a grace re-key connected robots live: a fleet of 50 and a real agent, none dropped."""

from __future__ import annotations

import asyncio
import os
import signal
import stat
import subprocess
import time
from datetime import datetime
from pathlib import Path

import pytest
from asgiref.sync import sync_to_async
from django.contrib.auth import get_user_model
from django.test import Client

from bridgeos_agent.link import AuthenticationError, Link
from bridgeos_agent.protocol import Event
from monitoring.models import Event as LogEvent
from robots.models import Robot
from tests.conftest import BIN, stop_process
from tests.logguard import watch

from .apiutil import async_client, make_owner, make_robot
from .wsutil import robot_link

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(120)]

FLEET = 50
AGENT_ROBOT = "rekey-agent"
# Short, so the test sees the old tokens expire; long enough for 51 rotations and their acks on 2 busy cores.
GRACE_S = 10.0


@sync_to_async
def log_kinds(kind: str) -> list[str]:
    return list(LogEvent.objects.filter(kind=kind).values_list("robot_id", flat=True))


@sync_to_async
def connected_ids() -> set[str]:
    return set(Robot.objects.filter(connected=True).values_list("id", flat=True))


async def until(check, what: str, timeout: float = 20.0) -> None:
    """Poll an async check until it holds."""
    deadline = time.monotonic() + timeout
    while not await check():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.1)


def start_agent(master: str, token_file: Path, data_dir: Path, log: Path) -> subprocess.Popen:
    """Start the real agent, simulated, taking its token from a file only."""
    command = [str(BIN / "bridgeos-agent"), "run", "--master", master, "--robot", AGENT_ROBOT]
    command += ["--token-file", str(token_file), "--runtime", "process", "--simulate", "--data-dir", str(data_dir)]
    env = {key: value for key, value in os.environ.items() if key != "BRIDGEOS_TOKEN"}
    with watch(log).open("ab") as out:
        return subprocess.Popen(command, env={**env, "PYTHONUNBUFFERED": "1"}, stdout=out, stderr=subprocess.STDOUT)


def logins(log: Path) -> int:
    """Count the agent's successful logins in its log."""
    return log.read_text(errors="replace").count("connected to the cloud (")


async def test_fifty_connected_robots_and_a_real_agent_re_key_with_a_grace_and_none_drops(daphne_server, tmp_path):
    alice, key = await make_owner("alice")
    old = {f"fleet-{i:02d}": await make_robot(alice, f"fleet-{i:02d}", with_skill=False) for i in range(FLEET)}
    old[AGENT_ROBOT] = await make_robot(alice, AGENT_ROBOT, with_skill=False)
    token_file = tmp_path / "robot.token"
    token_file.write_text(old[AGENT_ROBOT] + "\n")
    token_file.chmod(0o600)
    agent_log = tmp_path / "agent.log"
    agent = start_agent(daphne_server.ws_url, token_file, tmp_path / "agent-data", agent_log)
    links: dict[str, Link] = {}
    try:
        fleet = [robot_id for robot_id in old if robot_id != AGENT_ROBOT]
        connected = await asyncio.gather(*(robot_link(daphne_server, robot_id, old[robot_id]) for robot_id in fleet))
        links = dict(zip(fleet, connected, strict=True))

        async def all_connected() -> bool:
            return await connected_ids() == set(old)

        await until(all_connected, "the fleet and the agent to connect")

        async def agent_says_connected() -> bool:
            # The cloud marks the robot connected before the agent has read its answer and logged it.
            return logins(agent_log) == 1

        await until(agent_says_connected, "the agent to log that it is connected")

        # Rotate every robot's token through the API, as an organization admin does.
        new: dict[str, str] = {}
        valid_until: dict[str, datetime] = {}
        started = time.monotonic()
        async with async_client(daphne_server, key) as http:
            for robot_id in old:
                answer = await http.post(f"/api/robot/{robot_id}/token", json={"grace_s": GRACE_S})
                assert answer.status_code == 200, answer.text
                new[robot_id] = answer.json()["token"]
                valid_until[robot_id] = datetime.fromisoformat(answer.json()["old_token_valid_until"])
        rotated_in = time.monotonic() - started

        # Each light robot gets its own new token over its live connection (and its Link acks it).
        for robot_id, link in links.items():
            frame = await link.next(Event.ROBOT_REKEY, timeout=10)
            assert frame.data["token"] == new[robot_id]

        async def all_rekeyed() -> bool:
            return sorted(await log_kinds("robot_rekeyed")) == sorted(old)

        # Every robot acked, the real agent once its token file held the new token.
        await until(all_rekeyed, "every robot's ack of its new token")
        assert token_file.read_text().strip() == new[AGENT_ROBOT]
        assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
        assert "re-keyed: the cloud gave this robot a new token" in agent_log.read_text()
        # None dropped: no socket closed, no connection lost, the agent never logged in again.
        assert not [robot_id for robot_id, link in links.items() if link.closed.is_set()]
        assert await log_kinds(Event.CONNECTION_LOST) == []
        assert await connected_ids() == set(old)
        assert logins(agent_log) == 1
        assert sorted(await log_kinds("robot_token_rotated")) == sorted(old)

        # Within the grace the old token still logs in (this replaces that robot's connection).
        last = fleet[-1]
        assert time.time() < valid_until[last].timestamp() - 0.5, f"rotations took {rotated_in:.1f} s of the grace"
        within = await robot_link(daphne_server, last, old[last])
        await asyncio.wait_for(links[last].closed.wait(), 5)
        links[last] = within

        # After it, the old tokens are refused and every robot logs in with its new one.
        await asyncio.sleep(max(valid_until.values()).timestamp() - time.time() + 0.5)
        for robot_id in (fleet[0], last, AGENT_ROBOT):
            with pytest.raises(AuthenticationError):
                await robot_link(daphne_server, robot_id, old[robot_id])
        await asyncio.gather(*(link.close() for link in links.values()))
        again = await asyncio.gather(*(robot_link(daphne_server, robot_id, new[robot_id]) for robot_id in fleet))
        links = dict(zip(fleet, again, strict=True))
        assert all(not link.closed.is_set() for link in links.values())

        # The real agent logs in with its new token: its connection cut (replaced), then the agent restarted.
        cut = await robot_link(daphne_server, AGENT_ROBOT, new[AGENT_ROBOT])
        await cut.close()

        def agent_back(count: int):
            async def check() -> bool:
                assert agent.poll() is None, f"the agent exited with {agent.returncode}"
                return logins(agent_log) >= count and AGENT_ROBOT in await connected_ids()

            return check

        await until(agent_back(2), "the agent to log in again with its new token (in memory)")
        agent.send_signal(signal.SIGTERM)
        assert agent.wait(15) == 0
        agent = start_agent(daphne_server.ws_url, token_file, tmp_path / "agent-data", agent_log)
        await until(agent_back(3), "the restarted agent to log in with the token from its file")
        log_text = agent_log.read_text()
        assert new[AGENT_ROBOT] not in log_text and old[AGENT_ROBOT] not in log_text
        assert new[AGENT_ROBOT] not in daphne_server.log.read_text(errors="replace")
    finally:
        await asyncio.gather(*(link.close() for link in links.values()), return_exceptions=True)
        stop_process(agent)


async def test_a_rotation_without_grace_sends_no_token_and_closes_the_connection(daphne_server):
    alice, key = await make_owner("alice")
    link = await robot_link(daphne_server, "alice-bot", await make_robot(alice, "alice-bot", with_skill=False))
    async with async_client(daphne_server, key) as http:
        assert (await http.post("/api/robot/alice-bot/token", json={"grace_s": 0})).status_code == 200
    await asyncio.wait_for(link.closed.wait(), 5)
    assert link.close_code == 4004
    assert all(link.inbox.get_nowait().event != Event.ROBOT_REKEY for _ in range(link.inbox.qsize()))
    assert await log_kinds("robot_rekeyed") == []


async def test_the_admin_action_rotates_with_a_grace_and_re_keys_the_connected_robots_live(daphne_server):
    owner, _ = await make_owner("alice")
    online = await make_robot(owner, "online-bot", with_skill=False)
    offline = await make_robot(owner, "offline-bot", with_skill=False)
    link = await robot_link(daphne_server, "online-bot", online)
    try:

        @sync_to_async
        def rotate_in_the_admin() -> list[str]:
            get_user_model().objects.create_superuser("ops", password=None)
            admin = Client()
            admin.force_login(get_user_model().objects.get(username="ops"))
            answer = admin.post(
                "/admin/robots/robot/",
                {"action": "rotate_tokens", "_selected_action": ["online-bot", "offline-bot"]},
                follow=True,
            )
            assert answer.status_code == 200
            return [str(message) for message in answer.context["messages"]]

        said = await rotate_in_the_admin()
        frame = await link.next(Event.ROBOT_REKEY, timeout=10)
        assert any("1 of 2 robot(s) were connected" in line for line in said), said
        assert any(f"robot online-bot (shown only once): {frame.data['token']}" in line for line in said), said

        async def rekeyed() -> bool:
            return await log_kinds("robot_rekeyed") == ["online-bot"]

        await until(rekeyed, "the connected robot's ack")
        assert not link.closed.is_set()
        # The default grace (an hour) keeps both old tokens working meanwhile.
        await (await robot_link(daphne_server, "offline-bot", offline)).close()
        await (await robot_link(daphne_server, "online-bot", frame.data["token"])).close()
    finally:
        await link.close()
