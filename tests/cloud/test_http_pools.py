"""Reads stay fast while commands wait on a robot that does not answer: writes have threads of their own."""

from __future__ import annotations

import asyncio
import time

import pytest

from .apiutil import async_client, make_owner, make_robot
from .wsutil import robot_link

pytestmark = pytest.mark.django_db(transaction=True)


async def test_reads_answer_at_once_while_more_commands_than_threads_wait_on_a_silent_robot(daphne_server):
    owner, key = await make_owner("pools")
    token = await make_robot(owner, "silent-bot")
    link = await robot_link(daphne_server, "silent-bot", token)
    link.auto_ack = False
    try:
        async with async_client(daphne_server, key) as http:
            # More waiting commands than the server's 8 HTTP threads.
            # The last two wait for a free write thread (4 s) and then for the robot (4 s more); a busy
            # machine adds to that, so their own timeout is generous: what is timed is the read.
            commands = [
                asyncio.create_task(http.post("/api/robot/silent-bot/stop?wait=4", timeout=60)) for _ in range(10)
            ]
            await asyncio.sleep(0.5)
            started = time.monotonic()
            read = await http.get("/api/robot/silent-bot/info")
            elapsed = time.monotonic() - started
            answers = await asyncio.gather(*commands)
    finally:
        await link.close()
    assert read.status_code == 200
    assert elapsed < 2.0, f"a read waited {elapsed:.1f} s behind commands"
    assert [answer.status_code for answer in answers] == [504] * 10
