"""A command for a robot that is logging in reaches it after its login's answer, never before."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator
from typing import Any

import pytest
from asgiref.sync import sync_to_async
from channels.testing import WebsocketCommunicator
from django.db import connections

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Event
from bridgeos_cloud.loopowned import close_loop_objects
from robots import consumers, local
from robots.consumers import RobotConsumer
from robots.local import deliver, register_local
from robots.models import Robot

from .wsutil import make_owner, make_robot

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio]


@pytest.fixture(autouse=True)
async def in_process_consumers() -> AsyncIterator[None]:
    """Run the robot door in this process; close what its loop started, and its database connections, after."""
    yield
    await close_loop_objects()
    await sync_to_async(connections.close_all)()


class HeldIds:
    """The applied-ids store, whose load for a logging-in robot waits until the test lets it go on."""

    def __init__(self, store: Any) -> None:
        self.store, self.entered, self.release = store, asyncio.Event(), asyncio.Event()

    async def load(self, robot_id: str) -> list[str]:
        self.entered.set()
        await self.release.wait()
        return await self.store.load(robot_id)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.store, name)


async def test_a_command_delivered_during_the_login_follows_authentication_success(monkeypatch) -> None:
    owner, _ = await make_owner("login-order")
    token = await make_robot("order-bot", owner, with_skill=False)
    held = HeldIds(consumers.applied_ids())
    monkeypatch.setattr(consumers, "applied_ids", lambda: held)
    robot = WebsocketCommunicator(RobotConsumer.as_asgi(), "/ws/robot/")
    assert (await robot.connect())[0]

    login = protocol.make(Event.AUTHENTICATION_ROBOT, {"robot": "order-bot", "token": token}, now=time.time())
    await robot.send_to(text_data=protocol.encode(login))
    # Marked connected, its channel stored, and its answer not yet sent: the moment a command came.
    await asyncio.wait_for(held.entered.wait(), 10)
    channel = await sync_to_async(lambda: Robot.objects.get(id="order-bot").channel)()
    command = protocol.make(Event.SKILL_START, {"skill": "people-detection"}, now=time.time())
    message = {"type": "robot.command", "id": command.id, "frame": protocol.encode(command)}
    delivering = asyncio.ensure_future(deliver(channel, {**message, "reply_channel": Replies.channel_name}))
    await asyncio.sleep(0.2)
    held.release.set()
    await asyncio.wait_for(delivering, 10)

    events = [json.loads(await robot.receive_from(timeout=5))["event"] for _ in range(4)]
    assert events[0] == Event.AUTHENTICATION_SUCCESS
    assert Event.SKILL_START in events[1:]
    await robot.disconnect()


class Replies:
    """Where relay_command waits for answers, in this process."""

    channel_name = "specific.test!order-replies"

    def __init__(self) -> None:
        self.messages: asyncio.Queue[dict] = asyncio.Queue()

    async def dispatch(self, message: dict) -> None:
        await self.messages.put(message)


async def test_a_command_waiting_on_a_login_that_is_refused_is_answered_offline() -> None:
    owner, _ = await make_owner("login-refused")
    await make_robot("refused-bot", owner, with_skill=False)
    replies = Replies()
    register_local(replies)
    before = set(local._local)
    robot = WebsocketCommunicator(RobotConsumer.as_asgi(), "/ws/robot/")
    assert (await robot.connect())[0]
    (channel,) = set(local._local) - before

    command = protocol.make(Event.SKILL_START, {"skill": "people-detection"}, now=time.time())
    message = {"type": "robot.command", "id": command.id, "frame": protocol.encode(command)}
    delivering = asyncio.ensure_future(deliver(channel, {**message, "reply_channel": replies.channel_name}))
    wrong = protocol.make(
        Event.AUTHENTICATION_ROBOT, {"robot": "refused-bot", "token": "not-its-token"}, now=time.time()
    )
    await robot.send_to(text_data=protocol.encode(wrong))

    assert json.loads(await robot.receive_from(timeout=5))["event"] == Event.AUTHENTICATION_FAILURE
    await asyncio.wait_for(delivering, 10)
    assert await asyncio.wait_for(replies.messages.get(), 5) == {
        "type": "robot.reply",
        "offline": True,
        "id": command.id,
    }
    assert (await robot.receive_output(timeout=5))["type"] == "websocket.close"
