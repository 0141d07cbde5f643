"""The agent killed with kill -9 and restarted does not apply a command the cloud resends a second time."""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import subprocess
import time
from pathlib import Path

import psutil
import pytest
import websockets

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Envelope, Event
from bridgeos_agent.skillconfig import parse_skill_config
from tests.conftest import BIN
from tests.logguard import watch

pytestmark = pytest.mark.timeout(120)

SKILL = "restart-dedup"
COMMAND = ["sleep", "617"]  # a number no other test uses, so leftovers are ours to find


class ScriptedCloud:
    """A cloud on a real socket that acks what the robot sends and lets the test send it commands.

    Today's cloud resends an unacked command only on the connection it sent it on; this one
    resends over the next connection too, which is what a cloud that outlives the agent may do.
    """

    def __init__(self) -> None:
        self.frames: list[Envelope] = []
        self.ws = None
        self.connected = asyncio.Event()

    async def serve(self, ws) -> None:
        auth = protocol.decode(await ws.recv())
        robot = auth.data["robot"]
        await ws.send(protocol.encode(protocol.make(Event.AUTHENTICATION_SUCCESS, {"robot": robot}, now=time.time())))
        await ws.send(protocol.encode(protocol.make(Event.ROBOT_CONFIG, {"config": {}}, now=time.time())))
        self.ws = ws
        self.connected.set()
        with contextlib.suppress(websockets.ConnectionClosed):
            async for raw in ws:
                envelope = protocol.decode(raw)
                self.frames.append(envelope)
                if envelope.event in protocol.REQUIRES_ACK:
                    await ws.send(protocol.ack_text(envelope.id, now=time.time()))

    async def send(self, text: str) -> None:
        await self.ws.send(text)

    async def wait_for(self, what: str, check, timeout: float = 30.0) -> Envelope:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for envelope in self.frames:
                if check(envelope):
                    return envelope
            await asyncio.sleep(0.05)
        raise AssertionError(f"the robot never sent {what}; it sent {[f.event for f in self.frames]}")

    def statuses(self) -> list[str]:
        return [f.data["status"] for f in self.frames if f.event == Event.SKILL_STATUS and f.data["skill"] == SKILL]


def start_agent(port: int, data_dir: Path, log: Path) -> subprocess.Popen:
    with watch(log).open("ab") as out:
        return subprocess.Popen(
            [
                str(BIN / "bridgeos-agent"),
                "run",
                "--master",
                f"ws://127.0.0.1:{port}",
                "--robot",
                "dedup-1",
                "--token",
                "token",
                "--data-dir",
                str(data_dir),
                "--runtime",
                "process",
                "--simulate",
            ],
            stdout=out,
            stderr=subprocess.STDOUT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )


def our_workers() -> list[psutil.Process]:
    found = []
    for process in psutil.process_iter(["cmdline"]):
        if process.info["cmdline"] == COMMAND:
            found.append(process)
    return found


def skill_start_text() -> str:
    config = parse_skill_config(
        {
            "skill": "Restart dedup",
            "skill_id": SKILL,
            "components": {
                "worker": {
                    "name": "Worker",
                    "location": "robot",
                    "ros": False,
                    "resources": {"cpu": 0.1, "ram": 16},
                    "robot": {"command": COMMAND},
                }
            },
        }
    ).model_dump(mode="json")
    return protocol.encode(protocol.make(Event.SKILL_START, {"skill": SKILL, "config": config}, now=time.time()))


def answers(command_id: str):
    return lambda f: f.reply_to == command_id and f.event == Event.ACK


async def test_a_command_resent_after_kill_9_and_restart_is_answered_not_applied_again(tmp_path):
    cloud = ScriptedCloud()
    log = tmp_path / "agent.log"
    async with websockets.serve(cloud.serve, "127.0.0.1", 0) as server:
        port = server.sockets[0].getsockname()[1]
        agent = start_agent(port, tmp_path / "agent", log)
        try:
            await asyncio.wait_for(cloud.connected.wait(), 30)
            start = skill_start_text()
            start_id = protocol.decode(start).id
            await cloud.send(start)
            await cloud.wait_for("the start's ack", answers(start_id))
            await cloud.wait_for(
                "skill running", lambda f: f.event == Event.SKILL_STATUS and f.data["status"] == "running"
            )
            stop = protocol.make(Event.SKILL_STOP, {"skill": SKILL}, now=time.time())
            await cloud.send(protocol.encode(stop))
            await cloud.wait_for("the stop's ack", answers(stop.id))
            await cloud.wait_for(
                "skill stopped", lambda f: f.event == Event.SKILL_STATUS and f.data["status"] == "stopped"
            )
            assert not our_workers()
            await asyncio.sleep(0.5)  # the state file is written 0.2 s after a change

            agent.send_signal(signal.SIGKILL)
            agent.wait(10)
            cloud.connected.clear()
            cloud.frames.clear()
            agent = start_agent(port, tmp_path / "agent", log)
            await asyncio.wait_for(cloud.connected.wait(), 30)

            # The cloud never heard the start's ack (say) and sends it again, same id.
            await cloud.send(start)
            await cloud.wait_for("an answer to the resent start", answers(start_id))
            await asyncio.sleep(2.0)
            assert "starting" not in cloud.statuses() and "running" not in cloud.statuses(), log.read_text()[-3000:]
            assert not our_workers(), "the resent start was applied a second time"

            # A new start (new id) is applied as usual: the restarted agent does apply commands.
            again = skill_start_text()
            await cloud.send(again)
            await cloud.wait_for("the new start's ack", answers(protocol.decode(again).id))
            await cloud.wait_for(
                "skill running", lambda f: f.event == Event.SKILL_STATUS and f.data["status"] == "running"
            )
            assert len(our_workers()) == 1
            stop = protocol.make(Event.SKILL_STOP, {"skill": SKILL}, now=time.time())
            await cloud.send(protocol.encode(stop))
            await cloud.wait_for(
                "skill stopped", lambda f: f.event == Event.SKILL_STATUS and f.data["status"] == "stopped"
            )
        finally:
            if agent.poll() is None:
                agent.terminate()
                try:
                    agent.wait(15)
                except subprocess.TimeoutExpired:
                    agent.kill()
            for worker in our_workers():
                worker.kill()
