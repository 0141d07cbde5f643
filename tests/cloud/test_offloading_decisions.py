"""The Skill Managers' move log: offloading_decision events stored, mirrored to clients, listed by the API."""

from __future__ import annotations

import asyncio
import json
import time

import httpx
import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.protocol import Event
from monitoring.models import Event as LogEvent

from .wsutil import client_link, new_robot_link

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio, pytest.mark.timeout(120)]


def decision(**changes: object) -> dict:
    """Return a move of the sample Skill's detector to the cloud, as a manager reports it."""
    data = {
        "skill": "people-detection",
        "component": "detector",
        "location": "robot",
        "target": "cloud",
        "outcome": "moved",
        "reason": "estimate above threshold + hysteresis",
        "policy": "performance",
        "cost_robot": 0.8,
        "cost_cloud": 0.1,
        "estimated_reward": 0.7,
        "threshold": 0.2,
        "hysteresis": 0.05,
        "trained": False,
        "samples_seen": 12,
        "inputs": {"cpu_available": 0.1, "location": "robot", "cost_robot": 0.8, "cost_cloud": 0.1},
        "decided_at": time.time() - 2,
        "duration_s": 0.4,
    }
    data.update(changes)
    return data


@sync_to_async
def logged(robot_id: str) -> list[LogEvent]:
    return list(LogEvent.objects.filter(robot_id=robot_id, kind="offloading_decision").order_by("ts"))


async def test_a_move_is_stored_as_an_event_and_reaches_the_owner_live(daphne_server):
    robot, api_token = await new_robot_link(daphne_server, "alice-bot", "alice")
    client = await client_link(daphne_server, api_token)
    sent = await robot.send(Event.OFFLOADING_DECISION, decision())
    await robot.wait_acked(sent)
    live = await client.next(Event.OFFLOADING_DECISION)
    assert live.data["robot"] == "alice-bot" and live.data["outcome"] == "moved"
    assert live.data["cost_robot"] == 0.8 and live.data["inputs"]["location"] == "robot"
    failed = await robot.send(
        Event.OFFLOADING_DECISION, decision(outcome="failed", target="robot", location="cloud", error="no room")
    )
    await robot.wait_acked(failed)
    rows = await logged("alice-bot")
    assert [row.data["outcome"] for row in rows] == ["moved", "failed"]
    moved, refused = rows
    assert (moved.skill, moved.component, moved.source, moved.level) == (
        "people-detection",
        "detector",
        "manager",
        "info",
    )
    assert moved.data["estimated_reward"] == 0.7 and moved.data["duration_s"] == 0.4
    # Stored at the time the manager decided, not when the frame arrived.
    assert abs(moved.ts.timestamp() - decision()["decided_at"]) < 5
    assert refused.level == "warning" and "no room" in refused.message
    # A resent frame (same id) is acknowledged again but stored once.
    await robot.send_envelope(sent)
    await robot.wait_acked(sent)
    assert len(await logged("alice-bot")) == 2
    # The dashboard reads the log through the Robot API.
    async with httpx.AsyncClient(base_url=daphne_server.url, timeout=30) as http:
        answer = await http.get(
            "/api/events",
            params={"robot": "alice-bot", "kind": "offloading_decision"},
            headers={"Authorization": f"Token {api_token}"},
        )
    assert answer.status_code == 200
    assert [row["data"]["outcome"] for row in answer.json()["results"]] == ["failed", "moved"]
    await asyncio.gather(robot.close(), client.close())


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        ({"outcome": "maybe"}, "data.outcome"),
        ({"target": "either"}, "data.target"),
        ({"cost_robot": "high"}, "data.cost_robot"),
        ({"duration_s": -1.0}, "data.duration_s"),
        ({"inputs": {f"k{n}": 1.0 for n in range(40)}}, "data.inputs"),
    ],
)
async def test_a_malformed_decision_is_refused_and_nothing_is_stored(daphne_server, changes, field):
    robot, _ = await new_robot_link(daphne_server, "r1")
    await robot.ws.send(
        '{"event":"offloading_decision","id":"d-1","reply_to":null,"ts":1.0,"data":'
        + json.dumps(decision(**changes))
        + "}"
    )
    error = await robot.next(Event.ERROR_MESSAGE)
    assert error.reply_to == "d-1" and error.data["field"].startswith(field)
    assert await logged("r1") == []
    await robot.close()


async def test_a_decision_about_an_unknown_component_is_refused(daphne_server):
    robot, _ = await new_robot_link(daphne_server, "r1")
    sent = await robot.send(Event.OFFLOADING_DECISION, decision(component="nope"))
    error = await robot.next(Event.ERROR_MESSAGE)
    assert error.reply_to == sent.id and error.data["code"] == "not_found"
    assert await logged("r1") == []
    await robot.close()
