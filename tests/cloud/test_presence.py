"""Robots held by a daphne process that dies without a goodbye (kill -9) go offline: two real daphnes."""

from __future__ import annotations

import asyncio
import signal
import time

import httpx
import pytest
from asgiref.sync import sync_to_async

from monitoring.models import Event as LogEvent
from robots.models import Robot
from robots.presence import DEAD_PROCESS_REASON

from ..conftest import another_daphne
from .wsutil import make_owner, make_robot, robot_link

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio]

# The doomed process's liveness key lives this long; the surviving daphne sweeps every 2 s (the default).
DOOMED_TTL_S = 2
OFFLINE_WITHIN_S = 15.0


@pytest.fixture
def doomed_daphne(daphne_server, tmp_path):
    """Start a second daphne on the same database and Redis, to be killed by the test."""
    with another_daphne(tmp_path / "doomed.log", BRIDGEOS_PROCESS_TTL_S=str(DOOMED_TTL_S)) as started:
        yield started


@sync_to_async
def connected(robot_id: str) -> bool:
    return Robot.objects.get(id=robot_id).connected


@sync_to_async
def lost_reasons(robot_id: str) -> list[str]:
    return [e.data["reason"] for e in LogEvent.objects.filter(robot_id=robot_id, kind="connection_lost")]


async def test_robot_of_a_killed_process_goes_offline_and_commands_get_409(daphne_server, doomed_daphne):
    doomed, process = doomed_daphne
    owner, api_token = await make_owner("owner")
    stranded = [f"stranded-{i}" for i in range(3)]
    stranded_links = [await robot_link(doomed, robot_id, await make_robot(robot_id, owner)) for robot_id in stranded]
    survivor = await make_robot("survivor", owner, with_skill=False)
    survivor_link = await robot_link(daphne_server, "survivor", survivor)
    assert all([await connected(robot_id) for robot_id in [*stranded, "survivor"]])

    process.send_signal(signal.SIGKILL)
    process.wait(timeout=10)
    killed = time.monotonic()
    async with asyncio.timeout(OFFLINE_WITHIN_S):
        while any([await connected(robot_id) for robot_id in stranded]):
            await asyncio.sleep(0.1)
    took = time.monotonic() - killed

    assert took < OFFLINE_WITHIN_S
    for robot_id in stranded:
        assert await lost_reasons(robot_id) == [DEAD_PROCESS_REASON]
    # The live process's robot is not taken for an orphan.
    assert await connected("survivor") and await lost_reasons("survivor") == []
    async with httpx.AsyncClient(base_url=daphne_server.url) as http:
        headers = {"Authorization": f"Token {api_token}"}
        response = await http.post("/api/robot/stranded-0/start", headers=headers, params={"wait": "2"})
    assert response.status_code == 409, response.text
    await survivor_link.close()
    for link in stranded_links:
        await link.close()
