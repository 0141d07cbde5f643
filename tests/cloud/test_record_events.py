"""Event-log entries recorded together (a connect storm's batch): stored, and shown live as each stored row."""

from __future__ import annotations

import asyncio

import pytest
from asgiref.sync import sync_to_async
from channels.layers import get_channel_layer
from django.contrib.auth import get_user_model
from django.db import connections, transaction

from bridgeos_cloud.loopowned import close_loop_objects
from monitoring.choices import Level, Source
from monitoring.live import LIVE_GROUP, log_event_frame
from monitoring.models import Event
from monitoring.services import record_events
from robots.services import create_robot

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio]

TEST_REDIS_URL = "redis://127.0.0.1:6379/13"

ENTRIES = [
    {"message": "Robot ev-1 connected", "robot_id": "ev-1", "kind": "connection_established"},
    {
        # A robot's texts may hold a NUL byte, which PostgreSQL refuses: stored as U+FFFD.
        "message": "Robot ev-2 disconnected: gone\x00",
        "robot_id": "ev-2",
        "level": Level.WARNING,
        "kind": "connection_lost",
        "data": {"reason": "gone\x00", "tries": 3, "share": 0.5},
    },
    {"message": "Robot ev-1 registered its labels", "robot_id": "ev-1", "kind": "robot_labels_registered"},
]


@pytest.fixture
def redis_layer(settings) -> None:
    settings.CHANNEL_LAYERS = {
        "default": {"BACKEND": "channels_redis.core.RedisChannelLayer", "CONFIG": {"hosts": [TEST_REDIS_URL]}}
    }


@sync_to_async
def make_robots() -> None:
    owner = get_user_model().objects.create_user("events-owner")
    create_robot("ev-1", owner)
    create_robot("ev-2", owner)


@sync_to_async
def record(entries: list[dict]) -> list[Event]:
    with transaction.atomic():
        record_events(entries)
    return list(Event.objects.filter(kind__in={e["kind"] for e in entries}).order_by("id"))


async def live_entries(layer, channel: str, ids: set[int]) -> list[dict]:
    """Read the live group's messages until the entries with these ids were shown (others: skipped)."""
    shown: list[dict] = []
    while {m["frame"]["data"]["id"] for m in shown} != ids:
        message = await asyncio.wait_for(layer.receive(channel), timeout=5)
        for m in message["events"] if message["type"] == "live.events" else [message]:
            if m["frame"]["event"] == "log_event" and m["frame"]["data"]["id"] in ids:
                shown.append(m)
    return shown


async def test_entries_recorded_together_are_stored_and_shown_live_as_their_stored_rows(redis_layer) -> None:
    await make_robots()
    layer = get_channel_layer()
    channel = await layer.new_channel()
    await layer.group_add(LIVE_GROUP, channel)
    try:
        batch = await record(ENTRIES)
        shown = await live_entries(layer, channel, {e.id for e in batch})
    finally:
        await layer.group_discard(LIVE_GROUP, channel)
        await close_loop_objects()
        await sync_to_async(connections.close_all)()  # the thread's, so the test database can be dropped

    assert [(e.robot_id, e.level, e.source, e.kind, e.message, e.data) for e in batch] == [
        ("ev-1", Level.INFO, Source.CLOUD, "connection_established", "Robot ev-1 connected", {}),
        (
            "ev-2",
            Level.WARNING,
            Source.CLOUD,
            "connection_lost",
            "Robot ev-2 disconnected: gone\ufffd",
            {"reason": "gone\ufffd", "tries": 3, "share": 0.5},
        ),
        ("ev-1", Level.INFO, Source.CLOUD, "robot_labels_registered", "Robot ev-1 registered its labels", {}),
    ]
    assert len({e.ts for e in batch}) == 1
    # Live, in order, each entry is the frame its stored row makes (the envelope's id and time its own).
    assert [(m["robot"], m["frame"]["data"]) for m in shown] == [
        (e.robot_id, log_event_frame(e)[1]["data"]) for e in batch
    ]
