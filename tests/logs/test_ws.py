"""Logs over real sockets: a robot ships lines through /ws/robot/, clients tail them over /ws/client/."""

from __future__ import annotations

import asyncio
import time

import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.protocol import Event
from logs.models import ComponentLog
from logs.services import store_lines
from monitoring.models import Event as LogEvent
from tests.cloud.wsutil import client_link, make_owner, make_robot, robot_link
from tests.conftest import eventually

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio]

SKILL = "people-detection"


def lines(first: int, count: int, text: str = "line") -> list[dict]:
    now = time.time()
    return [
        {"seq": seq, "ts": now + seq / 1000, "stream": "stdout", "level": "info", "text": f"{text} {seq}"}
        for seq in range(first, first + count)
    ]


@sync_to_async
def stored(robot_id: str, component: str = "detector", location: str = "robot") -> list[int]:
    rows = ComponentLog.objects.filter(robot_id=robot_id, component=component, location=location)
    return list(rows.order_by("seq").values_list("seq", flat=True))


async def pushed(viewer, timeout: float = 5):
    """Return the next pushed component_logs frame (answers to requests also reach the inbox: skipped)."""
    async with asyncio.timeout(timeout):
        while True:
            frame = await viewer.next(Event.COMPONENT_LOGS, timeout=timeout)
            if frame.reply_to is None:
                return frame


async def owner_and_robot(server, robot_id: str, username: str):
    user, api_token = await make_owner(username)
    link = await robot_link(server, robot_id, await make_robot(robot_id, user))
    return link, api_token


async def test_a_robots_lines_are_stored_once_however_often_they_come(daphne_server):
    link, _ = await owner_and_robot(daphne_server, "lw-door", "lw-door-user")
    frame = {"skill": SKILL, "component": "detector", "lines": lines(1, 500), "dropped": 3}
    first = await link.send(Event.COMPONENT_LOGS, frame)
    await link.wait_acked(first)
    # The very same frame again (a resend), and another frame carrying the same lines: each acked, stored once.
    await link.send_envelope(first)
    again = await link.send(Event.COMPONENT_LOGS, frame)
    await link.wait_acked(again)
    assert await stored("lw-door") == list(range(1, 501))
    await link.close()


async def test_a_robot_cannot_ship_lines_for_another_robot(daphne_server):
    link, _ = await owner_and_robot(daphne_server, "lw-self", "lw-self-user")
    await owner_and_robot(daphne_server, "lw-other", "lw-other-user")
    data = {"robot": "lw-other", "skill": SKILL, "component": "detector", "lines": lines(1, 2)}
    await link.send(Event.COMPONENT_LOGS, data)
    refused = await link.next(Event.ERROR_MESSAGE)
    assert refused.data["field"] == "data.robot"
    assert await stored("lw-other") == []
    await link.close()


async def test_a_crash_event_carries_the_components_last_lines(daphne_server):
    link, _ = await owner_and_robot(daphne_server, "lw-crash", "lw-crash-user")
    last = lines(41, 3, "Traceback")
    report = {"skill": SKILL, "component": "detector", "status": "failed", "message": "exited 1", "last_lines": last}
    await link.wait_acked(await link.send(Event.COMPONENT_STATUS, report))
    event = await sync_to_async(
        lambda: LogEvent.objects.filter(robot_id="lw-crash", kind=Event.COMPONENT_STATUS).latest("ts")
    )()
    assert event.data["status"] == "failed"
    assert [row["text"] for row in event.data["lines"]] == ["Traceback 41", "Traceback 42", "Traceback 43"]
    assert event.data["lines"][0]["seq"] == 41
    await link.close()


async def test_a_live_tail_starts_from_the_last_lines_then_streams_new_ones(daphne_server):
    link, api_token = await owner_and_robot(daphne_server, "lw-tail", "lw-tail-user")
    await link.wait_acked(
        await link.send(Event.COMPONENT_LOGS, {"skill": SKILL, "component": "detector", "lines": lines(1, 30)})
    )
    await asyncio.sleep(
        0.3
    )  # those lines' own push (to nobody yet) is done: a subscriber right away may get them twice
    viewer = await client_link(daphne_server, api_token)
    subscribe = {"robot": "lw-tail", "skill": SKILL, "component": "detector", "tail": 10}
    backlog = await viewer.request(Event.LOGS_SUBSCRIBE, subscribe)
    assert backlog.event == Event.COMPONENT_LOGS
    assert backlog.data["robot"] == "lw-tail"
    assert [line["seq"] for line in backlog.data["lines"]] == list(range(21, 31))
    started = time.monotonic()
    await link.send(Event.COMPONENT_LOGS, {"skill": SKILL, "component": "detector", "lines": lines(31, 2, "fresh")})
    pushed_frame = await pushed(viewer)
    assert time.monotonic() - started < 2
    assert pushed_frame.reply_to is None
    assert [line["text"] for line in pushed_frame.data["lines"]] == ["fresh 31", "fresh 32"]
    # Another component's lines are not this tail's; after logs_unsubscribe nothing comes.
    await link.send(Event.COMPONENT_LOGS, {"skill": SKILL, "component": "sampler", "lines": lines(1, 1)})
    unsubscribed = await viewer.request(
        Event.LOGS_UNSUBSCRIBE, {"robot": "lw-tail", "skill": SKILL, "component": "detector"}
    )
    assert unsubscribed.event == Event.ACK
    await link.send(Event.COMPONENT_LOGS, {"skill": SKILL, "component": "detector", "lines": lines(33, 1)})
    await eventually(lambda: stored("lw-tail"), what="the last line stored")
    with pytest.raises(TimeoutError):
        await pushed(viewer, timeout=1)
    await viewer.close()
    await link.close()


async def test_a_tail_of_a_quiet_component_is_answered_and_another_users_robot_is_not_found(daphne_server):
    _, api_token = await owner_and_robot(daphne_server, "lw-quiet", "lw-quiet-user")
    await owner_and_robot(daphne_server, "lw-foreign", "lw-foreign-user")
    viewer = await client_link(daphne_server, api_token)
    empty = await viewer.request(Event.LOGS_SUBSCRIBE, {"robot": "lw-quiet", "skill": SKILL, "component": "detector"})
    assert empty.event == Event.COMPONENT_LOGS and empty.data["lines"] == []
    whole = await viewer.request(Event.LOGS_SUBSCRIBE, {"robot": "lw-quiet"})
    assert whole.event == Event.ACK
    refused = await viewer.request(Event.LOGS_SUBSCRIBE, {"robot": "lw-foreign"})
    assert refused.event == Event.ERROR_MESSAGE and refused.data["code"] == "not_found"
    # Lines of the robot the viewer may not see never reach it.
    await sync_to_async(store_lines)("lw-foreign", SKILL, "detector", "robot", lines(1, 1))
    with pytest.raises(TimeoutError):
        await pushed(viewer, timeout=1)
    await viewer.close()


async def test_a_tail_asking_for_the_ring_gets_the_lines_the_robot_never_shipped(daphne_server):
    link, api_token = await owner_and_robot(daphne_server, "lw-ring", "lw-ring-user")
    await link.wait_acked(
        await link.send(Event.COMPONENT_LOGS, {"skill": SKILL, "component": "detector", "lines": lines(1, 5)})
    )
    await asyncio.sleep(0.3)
    viewer = await client_link(daphne_server, api_token)
    subscribe = {"robot": "lw-ring", "skill": SKILL, "component": "detector", "tail": 5, "ring": True}
    backlog = await viewer.request(Event.LOGS_SUBSCRIBE, subscribe)
    assert [line["seq"] for line in backlog.data["lines"]] == [1, 2, 3, 4, 5]
    # The robot is asked for what follows the newest stored line, and answers from its ring.
    asked = await link.next(Event.COMPONENT_LOGS_GET, timeout=5)
    assert asked.data["skill"] == SKILL and asked.data["component"] == "detector" and asked.data["after_seq"] == 5
    ring = {"skill": SKILL, "component": "detector", "lines": lines(6, 3, "from the ring")}
    answer = await link.send(Event.COMPONENT_LOGS, ring, reply_to=asked.id)
    await link.wait_acked(answer)
    pushed_frame = await pushed(viewer)
    assert [line["seq"] for line in pushed_frame.data["lines"]] == [6, 7, 8]
    assert await stored("lw-ring") == list(range(1, 9))
    await viewer.close()
    await link.close()


async def test_closing_the_client_socket_ends_its_tails(daphne_server):
    link, api_token = await owner_and_robot(daphne_server, "lw-close", "lw-close-user")
    viewer = await client_link(daphne_server, api_token)
    await viewer.request(Event.LOGS_SUBSCRIBE, {"robot": "lw-close", "skill": SKILL, "component": "detector"})
    await viewer.close()
    await asyncio.sleep(0.3)
    from channels.layers import get_channel_layer

    layer = get_channel_layer()
    members = await layer.connection(layer.consistent_hash("logs.lw-close")).zcard(layer._group_key("logs.lw-close"))
    assert members == 0
    await link.close()
