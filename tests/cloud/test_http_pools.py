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
            commands = [
                asyncio.create_task(http.post("/api/robot/silent-bot/stop?wait=4", timeout=120)) for _ in range(10)
            ]
            await asyncio.sleep(0.5)
            started = time.monotonic()
            read = await http.get("/api/robot/silent-bot/info")
            elapsed = time.monotonic() - started
            # Every command answers once its own 4 s wait is over, while the robot is still there: a
            # receive that absorbed its cancellation once kept one waiting until the robot left (409).
            done, pending = await asyncio.wait(commands, timeout=10)
            await link.close()
            answers = [task.result() for task in done] + list(await asyncio.gather(*pending))
    finally:
        await link.close()
    assert read.status_code == 200
    assert elapsed < 2.0, f"a read waited {elapsed:.1f} s behind commands"
    assert not pending, f"{len(pending)} commands were still waiting 10 s after their 4 s wait began"
    assert [answer.status_code for answer in answers] == [504] * 10


async def test_a_command_answers_after_its_wait_while_more_commands_than_read_threads_wait_on_another_robot(
    daphne_server,
):
    owner, key = await make_owner("pools2")
    silent = await robot_link(daphne_server, "silent-a", await make_robot(owner, "silent-a"))
    other = await robot_link(daphne_server, "silent-b", await make_robot(owner, "silent-b"))
    silent.auto_ack = other.auto_ack = False
    try:
        async with async_client(daphne_server, key) as http:
            # Half again as many as the server's 8 read threads, each waiting 6 s on robot a.
            waiting = [asyncio.create_task(http.post("/api/robot/silent-a/stop?wait=6", timeout=60)) for _ in range(12)]
            await asyncio.sleep(0.5)
            started = time.monotonic()
            answer = await http.post("/api/robot/silent-b/stop?wait=1", timeout=60)
            elapsed = time.monotonic() - started
            statuses = [response.status_code for response in await asyncio.gather(*waiting)]
    finally:
        await silent.close()
        await other.close()
    # Robot b answered nothing: 504 once its own wait is over, not once a thread came free.
    assert answer.status_code == 504, answer.text
    assert elapsed < 2.5, f"a 1 s command answered after {elapsed:.1f} s"
    assert statuses == [504] * 12
