"""A metrics frame resent after a crash (its ack lost) is stored once: the frame id commits with its rows."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from datetime import UTC, datetime, timedelta

import pytest
from asgiref.sync import sync_to_async
from django.contrib.auth import get_user_model
from django.db import connections

from bridgeos_agent.protocol import MetricPoint
from monitoring import services
from monitoring.ingest import MetricWriter
from monitoring.models import IngestedFrame, Metric
from robots.services import create_robot

pytestmark = pytest.mark.django_db(transaction=True)

T0 = 1_760_000_000.0


@pytest.fixture(autouse=True)
async def close_thread_connections() -> AsyncIterator[None]:
    yield
    await sync_to_async(connections.close_all)()


@pytest.fixture
def robot() -> str:
    owner = get_user_model().objects.create_user("owner")
    return create_robot("r1", owner)[0].id


def points(n: int, start: float = T0) -> list[MetricPoint]:
    return [MetricPoint(name="cpu", value=float(i), ts=start + i) for i in range(n)]


@sync_to_async
def stored_rows(robot_id: str) -> int:
    return Metric.objects.filter(robot_id=robot_id).count()


async def test_a_frame_resent_to_a_fresh_writer_is_stored_once(robot):
    # The first daphne committed the frame and died before its ack left; the robot resends it to a new one.
    first = MetricWriter(flush_interval=0.01)
    await first.add(robot, points(5), "frame-1")
    await first.close()
    second = MetricWriter(flush_interval=0.01)
    try:
        resent = second.add(robot, points(5), "frame-1")
        fresh = second.add(robot, points(3, T0 + 100), "frame-2")
        await asyncio.wait_for(asyncio.gather(resent, fresh), 10)
        assert second.rows_already_stored == 5
    finally:
        await second.close()
    assert await stored_rows(robot) == 8


async def test_the_same_frame_twice_in_one_batch_is_stored_once(robot):
    writer = MetricWriter(flush_interval=60)
    try:
        copies = [writer.add(robot, points(4), "frame-9"), writer.add(robot, points(4), "frame-9")]
        await writer.flush()
        await asyncio.gather(*copies)
    finally:
        await writer.close()
    assert await stored_rows(robot) == 4


async def test_a_failed_write_leaves_no_frame_id_behind(robot):
    # Points refused by the database roll back with their frame id: the robot's resend is then stored.
    writer = MetricWriter(flush_interval=0.01)
    try:
        with pytest.raises(Exception):  # noqa: B017 - whatever the database says about a NUL in a name
            await writer.add(robot, [MetricPoint(name="c\x00pu", value=1.0, ts=T0)], "frame-3")
        assert not await sync_to_async(IngestedFrame.objects.filter(frame_id="frame-3").exists)()
        await writer.add(robot, points(2), "frame-3")
    finally:
        await writer.close()
    assert await stored_rows(robot) == 2


def test_pruning_keeps_each_robots_newest_frame_ids(robot):
    old = datetime(2026, 1, 1, tzinfo=UTC)
    IngestedFrame.objects.bulk_create(
        [
            IngestedFrame(robot_id=robot, frame_id=f"f{i}", created=old)
            for i in range(services.INGESTED_FRAMES_KEPT_PER_ROBOT + 50)
        ]
    )
    other = create_robot("r2", get_user_model().objects.get(username="owner"))[0].id
    IngestedFrame.objects.create(robot_id=other, frame_id="young")
    IngestedFrame.objects.create(robot_id="deleted-robot", frame_id="young")

    deleted = services.prune_ingested_frames(now=old + timedelta(days=2))

    assert deleted == 51
    assert IngestedFrame.objects.filter(robot_id=robot).count() == services.INGESTED_FRAMES_KEPT_PER_ROBOT
    assert not IngestedFrame.objects.filter(robot_id=robot, frame_id="f0").exists()
    assert IngestedFrame.objects.filter(robot_id=other).exists()
    assert not IngestedFrame.objects.filter(robot_id="deleted-robot").exists()
