"""Every acked report is applied once, even when its id never reached Redis (a daphne killed before saving it).

The Redis window of applied ids is saved every couple of seconds; a robot that reconnects
(to this daphne or another) and resends an unacked frame is checked against that window and,
since issue 37, against the frame ids committed with the frame's effects.
"""

from __future__ import annotations

import asyncio

import pytest
import redis
from asgiref.sync import sync_to_async
from django.conf import settings

from bridgeos_agent.protocol import Event
from monitoring.models import Event as LogEvent
from robots.dedup import KEY
from robots.models import Robot

from .test_offloading_decisions import decision
from .wsutil import make_owner, make_robot, robot_link

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio, pytest.mark.timeout(120)]

FRAMES = {
    Event.OFFLOADING_DECISION: (decision(), "offloading_decision"),
    Event.COMPONENT_STATUS: (
        {"skill": "people-detection", "component": "detector", "status": "failed", "message": "exit 1"},
        "component_status",
    ),
}


@sync_to_async
def logged(robot_id: str, kind: str) -> int:
    return LogEvent.objects.filter(robot_id=robot_id, kind=kind).count()


@sync_to_async
def offline(robot_id: str) -> bool:
    return not Robot.objects.get(id=robot_id).connected


@pytest.mark.parametrize("event", list(FRAMES))
async def test_a_report_resent_after_its_id_was_lost_from_redis_is_applied_once(daphne_server, event):
    owner, _ = await make_owner("once")
    token = await make_robot("once-bot", owner)
    data, kind = FRAMES[event]
    link = await robot_link(daphne_server, "once-bot", token)
    try:
        sent = await link.send(event, data)
        await link.wait_acked(sent)
    finally:
        await link.close()
    assert await logged("once-bot", kind) == 1
    for _ in range(100):
        if await offline("once-bot"):
            break
        await asyncio.sleep(0.05)
    # What a daphne killed before its periodic save leaves: the frame applied, its id not in Redis.
    redis.Redis.from_url(settings.REDIS_URL).delete(KEY.format("once-bot"))
    again = await robot_link(daphne_server, "once-bot", token)
    try:
        await again.send_envelope(sent)
        await again.wait_acked(sent)
    finally:
        await again.close()
    assert await logged("once-bot", kind) == 1
