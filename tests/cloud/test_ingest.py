"""The batched metric writer, the coalescing live feed and metric pruning, on real PostgreSQL and Redis."""

from __future__ import annotations

import asyncio
import io
import json
import logging
import threading
import time
import uuid
from collections.abc import AsyncIterator, Callable
from datetime import UTC, datetime, timedelta
from typing import Any

import psycopg
import pytest
from asgiref.sync import sync_to_async
from channels.layers import InMemoryChannelLayer, get_channel_layer
from channels_redis.core import RedisChannelLayer
from django.contrib.auth import get_user_model
from django.core.management import call_command
from django.db import connections, transaction
from django.utils import timezone

from bridgeos_agent.protocol import MetricPoint
from bridgeos_cloud.loopowned import close_loop_objects
from monitoring import live
from monitoring.ingest import MetricWriter, get_writer
from monitoring.live import (
    LIVE_GROUP,
    LiveFeed,
    get_live_feed,
    has_members,
    metrics_data_json,
    publish_on_commit,
)
from monitoring.models import Metric
from monitoring.sinks import PostgresSink, conninfo_from_settings, format_ts
from robots.dedup import applied_ids
from robots.models import Robot
from robots.services import create_robot

pytestmark = pytest.mark.django_db(transaction=True)

# Its own Redis database: another suite may be using the default one right now.
TEST_REDIS_URL = "redis://127.0.0.1:6379/13"
T0 = 1_760_000_000.0


@pytest.fixture(autouse=True)
async def close_thread_connections() -> AsyncIterator[None]:
    yield
    # sync_to_async's thread keeps its own connection, which would block dropping the test database.
    await sync_to_async(connections.close_all)()


@pytest.fixture
def robots() -> list[str]:
    owner = get_user_model().objects.create_user("owner")
    return [create_robot(robot_id, owner)[0].id for robot_id in ("r1", "r2", "r3")]


@pytest.fixture
async def make_writer() -> AsyncIterator[Callable[..., MetricWriter]]:
    writers: list[MetricWriter] = []

    def make(**options: float) -> MetricWriter:
        writer = MetricWriter(**options)
        writers.append(writer)
        return writer

    yield make
    for writer in writers:
        await writer.close()


@pytest.fixture
def redis_layer(settings) -> None:
    settings.CHANNEL_LAYERS = {
        "default": {"BACKEND": "channels_redis.core.RedisChannelLayer", "CONFIG": {"hosts": [TEST_REDIS_URL]}}
    }


def point(name: str, value: float, ts: float, **fields: Any) -> MetricPoint:
    return MetricPoint(name=name, value=value, ts=ts, **fields)


@sync_to_async
def stored() -> list[tuple]:
    return list(
        Metric.objects.order_by("robot_id", "ts", "name").values_list(
            "robot_id", "skill", "component", "name", "value", "labels", "ts"
        )
    )


def expected(robot_id: str, points: list[MetricPoint]) -> list[tuple]:
    return [
        (
            robot_id,
            p.get("skill") or "",
            p.get("component") or "",
            p["name"],
            p["value"],
            p.get("labels") or {},
            datetime.fromtimestamp(p["ts"], UTC),
        )
        for p in points
    ]


async def test_points_of_several_robots_are_stored_exactly(robots, make_writer):
    writer = make_writer()
    sent = {
        robot_id: [
            point("cpu", 12.5 + i, T0 + i + 0.123456, skill="nav", component="planner", labels={"core": str(i)}),
            point("mem", 1e-300, T0 + i + 0.9999996),  # rounds up into the next second
            point("temp", -3.25, T0 + i + 0.0000005),  # half a microsecond: rounds half to even
        ]
        for i, robot_id in enumerate(robots)
    }

    await asyncio.gather(*(writer.add(robot_id, points) for robot_id, points in sent.items()))

    rows = await stored()
    assert rows == sorted(
        (row for robot_id, points in sent.items() for row in expected(robot_id, points)),
        key=lambda row: (row[0], row[6], row[3]),
    )
    assert all(row[6].utcoffset() == timedelta(0) for row in rows)
    assert writer.rows_written == 9 and writer.pending_rows == 0


@pytest.mark.parametrize("ts", [0.0, 0.0000005, 0.0000015, 1.9999995, T0 + 0.1234565, 4_102_444_799.9999996])
def test_timestamps_are_formatted_as_datetime_rounds_them(ts):
    assert format_ts(ts) == datetime.fromtimestamp(ts, UTC).strftime("%Y-%m-%d %H:%M:%S.%f+00")


async def test_future_resolves_only_once_rows_are_committed(robots, make_writer):
    writer = make_writer(flush_interval=60)
    seen_by_another_connection: list[int] = []

    def count_committed(_future: asyncio.Future[None]) -> None:
        # A connection of its own sees only committed rows.
        with psycopg.connect(conninfo_from_settings()) as conn:
            seen_by_another_connection.append(conn.execute("SELECT count(*) FROM monitoring_metric").fetchone()[0])

    future = writer.add("r1", [point("cpu", 1.0, T0), point("cpu", 2.0, T0 + 1)])
    future.add_done_callback(count_committed)
    await asyncio.sleep(0.3)
    assert not future.done()
    assert await stored() == []

    await writer.flush()

    assert future.done() and future.exception() is None
    assert seen_by_another_connection == [2]


async def test_a_full_buffer_flushes_before_the_interval(robots, make_writer):
    writer = make_writer(flush_rows=100, flush_interval=60)
    first = writer.add("r1", [point("cpu", float(i), T0 + i) for i in range(60)])
    await asyncio.sleep(0.3)
    assert not first.done()

    second = writer.add("r2", [point("cpu", float(i), T0 + i) for i in range(50)])

    await asyncio.wait_for(asyncio.gather(first, second), timeout=5)
    assert writer.batches == 1 and writer.rows_written == 110


async def test_the_interval_flushes_a_small_buffer(robots, make_writer):
    writer = make_writer(flush_rows=1_000_000, flush_interval=0.1)

    await asyncio.wait_for(writer.add("r1", [point("cpu", 1.0, T0)]), timeout=2)

    assert writer.batches == 1
    assert len(await stored()) == 1


async def test_labels_with_special_characters_round_trip(robots, make_writer):
    writer = make_writer()
    labels = {
        "tab": "a\tb",
        "newline": "a\nb\r\nc",
        "backslash": "C:\\path\\N",
        "quote": "say \"hi\" 'there'",
        "unicode": "Zürich ☃ 😀 \u2028",
        "json": '{"nested": [1, 2]}',
        "copy.null": "\\N",
        "empty": "",
    }

    await writer.add("r1", [point("cpu", 1.0, T0, labels=labels), point("cpu", 2.0, T0 + 1, labels=labels)])

    assert [row[5] for row in await stored()] == [labels, labels]


async def test_nul_characters_are_stripped_from_labels(robots, make_writer):
    writer = make_writer()

    await writer.add("r1", [point("cpu", 1.0, T0, labels={"host": "a\x00b"})])

    assert [row[5] for row in await stored()] == [{"host": "ab"}]


async def test_rows_of_a_deleted_robot_are_dropped_without_losing_others(robots, make_writer, caplog):
    writer = make_writer(flush_interval=60)
    kept = writer.add("r1", [point("cpu", float(i), T0 + i) for i in range(5)])
    dropped = writer.add("r2", [point("cpu", float(i), T0 + i) for i in range(5)])
    also_kept = writer.add("r3", [point("mem", 7.0, T0)])
    await sync_to_async(Robot.objects.filter(id="r2").delete)()

    with caplog.at_level(logging.WARNING, logger="monitoring.ingest"):
        await writer.flush()

    await asyncio.gather(kept, dropped, also_kept)
    assert {row[0] for row in await stored()} == {"r1", "r3"}
    assert len(await stored()) == 6
    assert writer.rows_written == 6 and writer.rows_dropped == 5
    assert [r.getMessage() for r in caplog.records] == ["Dropped 5 metric rows of deleted robots: r2"]


async def test_a_robot_deleted_while_a_batch_of_its_points_is_written_keeps_none_of_them(
    robots, make_writer, monkeypatch
):
    # Metric rows have no foreign key to their robot: the batch's lock on the robot's row and the
    # deletion's lock on it keep a committed batch from leaving points behind a deleted robot.
    locked, go_on = threading.Event(), threading.Event()
    claim = PostgresSink._claim

    def claim_once_the_test_says(self, cursor, entries):
        locked.set()  # the batch holds its robots' rows by now
        go_on.wait(10)
        return claim(self, cursor, entries)

    monkeypatch.setattr(PostgresSink, "_claim", claim_once_the_test_says)
    writer = make_writer(flush_interval=60)
    frame = writer.add("r2", [point("cpu", float(i), T0 + i) for i in range(5)])
    flushing = asyncio.ensure_future(writer.flush())
    assert await asyncio.to_thread(locked.wait, 10)
    delete = sync_to_async(Robot.objects.filter(id="r2").delete, thread_sensitive=False)
    deleting = asyncio.ensure_future(delete())
    await asyncio.sleep(0.5)
    assert not deleting.done(), "the deletion did not wait for the batch holding its robot"

    go_on.set()
    await asyncio.wait_for(asyncio.gather(flushing, frame, deleting), 15)
    assert writer.rows_written == 5
    assert await sync_to_async(Metric.objects.filter(robot_id="r2").count)() == 0


async def test_a_frame_the_database_refuses_fails_alone(robots, make_writer):
    writer = make_writer(flush_interval=60)
    good = writer.add("r1", [point("cpu", 1.0, T0)])
    # Built without validation: a name longer than the column allows.
    bad = writer.add("r2", [MetricPoint(name="x" * 200, value=1.0, ts=T0)])
    also_good = writer.add("r3", [point("cpu", 3.0, T0)])

    await writer.flush()

    assert good.exception() is None and also_good.exception() is None
    assert isinstance(bad.exception(), psycopg.DataError)
    assert [row[0] for row in await stored()] == ["r1", "r3"]


async def test_a_point_that_cannot_be_formatted_fails_its_frame_at_once(robots, make_writer):
    writer = make_writer()

    future = writer.add("r1", [point("cpu", 1.0, 1e14)])  # far beyond year 9999

    assert isinstance(future.exception(), ValueError | OverflowError)
    assert writer.pending_rows == 0


async def test_close_flushes_what_is_buffered(robots):
    writer = MetricWriter(flush_interval=60)
    future = writer.add("r1", [point("cpu", 1.0, T0)])

    await writer.close()

    assert future.done() and future.exception() is None
    assert len(await stored()) == 1


async def test_writer_reconnects_after_losing_its_connection(robots, make_writer, caplog):
    writer = make_writer()
    await writer.add("r1", [point("cpu", 1.0, T0)])
    admin_conninfo = psycopg.conninfo.make_conninfo(conninfo_from_settings(), application_name="test-admin")
    with psycopg.connect(admin_conninfo, autocommit=True) as admin:
        admin.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE application_name = %s",
            ["bridgeos-metric-writer"],
        )

    await asyncio.wait_for(writer.add("r1", [point("cpu", 2.0, T0 + 1)]), timeout=5)

    assert [row[4] for row in await stored()] == [1.0, 2.0]
    assert "retrying once" in caplog.text


async def test_get_writer_returns_one_writer_per_loop(robots):
    writer = get_writer()
    try:
        assert get_writer() is writer
        await writer.add("r1", [point("cpu", 1.0, T0)])
    finally:
        await writer.close()


async def test_the_loops_writer_feed_and_applied_ids_are_closed_by_their_owner_at_shutdown(robots, redis_layer):
    writer, feed, ids = get_writer(), get_live_feed(), applied_ids()
    pending = writer.add("r1", [point("cpu", 1.0, T0)])
    feed.add_metrics("r1", [point("cpu", 1.0, T0)])
    ids.add("r1", "frame-1")

    await close_loop_objects()

    # Closing flushed what was pending: the row is stored and the id saved.
    assert pending.done() and pending.exception() is None
    assert [row[:5] for row in await stored()] == [("r1", "", "", "cpu", 1.0)]
    assert writer.closed and feed._task is None
    # The next use in this loop gets fresh ones, owned again.
    assert get_writer() is not writer and get_live_feed() is not feed and applied_ids() is not ids
    assert "frame-1" in await applied_ids().load("r1")
    await close_loop_objects()


async def test_live_feed_coalesces_many_adds_into_one_message_of_latest_values(redis_layer):
    layer = get_channel_layer()
    channel = await layer.new_channel()
    await layer.group_add(LIVE_GROUP, channel)
    feed = LiveFeed(interval=0.3)
    try:
        for i in range(100):
            feed.add_metrics("r1", [point("cpu", float(i), T0 + i), point("mem", 2.0 * i, T0 + i, skill="nav")])
            feed.add_metrics("r2", [point("cpu", -float(i), T0 + i, skill="nav", component="planner")])
        # A resent older point must not replace the newer value.
        feed.add_metrics("r1", [point("cpu", -1.0, T0)])

        message = await asyncio.wait_for(layer.receive(channel), timeout=3)

        assert message["type"] == "live.metrics"
        assert {robot: json.loads(data) for robot, data in message["robots"].items()} == {
            "r1": {
                "robot": "r1",
                "metrics": [
                    {"name": "cpu", "value": 99.0, "ts": T0 + 99},
                    {"name": "mem", "value": 198.0, "ts": T0 + 99, "skill": "nav"},
                ],
            },
            "r2": {
                "robot": "r2",
                "metrics": [{"name": "cpu", "value": -99.0, "ts": T0 + 99, "skill": "nav", "component": "planner"}],
            },
        }
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(layer.receive(channel), timeout=0.8)
        assert feed.messages_sent == 1
    finally:
        await feed.close()
        await layer.group_discard(LIVE_GROUP, channel)
        await layer.close_pools()


async def test_live_feed_encodes_and_sends_nothing_while_nobody_watches(monkeypatch):
    monkeypatch.setattr(live, "UNWATCHED_RECHECK_S", 0.3)
    # A layer of its own (its own key prefix), so no other test's watcher is in its live group.
    layer = RedisChannelLayer(hosts=[TEST_REDIS_URL], prefix=f"unwatched-{uuid.uuid4().hex}")
    feed = LiveFeed(interval=0.05, layer=layer)
    try:
        feed.add_metrics("r1", [point("cpu", 1.0, T0)])
        await wait_for_condition(lambda: feed.unwatched_sends == 1)
        assert feed.messages_sent == 0

        channel = await layer.new_channel()
        await layer.group_add(LIVE_GROUP, channel)
        # Nobody watched a moment ago: not even gathered, until the feed looks again.
        feed.add_metrics("r1", [point("cpu", 2.0, T0 + 1)])
        assert not feed._latest
        await asyncio.sleep(0.3)
        feed.add_metrics("r1", [point("cpu", 3.0, T0 + 2)])
        message = await asyncio.wait_for(layer.receive(channel), timeout=3)

        # Only what arrived once someone watched: the values nobody was there for are gone.
        assert json.loads(message["robots"]["r1"])["metrics"] == [{"name": "cpu", "value": 3.0, "ts": T0 + 2}]
        assert feed.messages_sent == 1 and feed.unwatched_sends == 1
        await layer.group_discard(LIVE_GROUP, channel)
    finally:
        await feed.close()
        await layer.close_pools()


async def test_the_in_memory_layer_says_whether_a_group_has_members():
    layer = InMemoryChannelLayer()
    assert not await has_members(layer, LIVE_GROUP)
    await layer.group_add(LIVE_GROUP, await layer.new_channel())
    assert await has_members(layer, LIVE_GROUP)


async def wait_for_condition(condition: Callable[[], bool], timeout: float = 3.0) -> None:
    deadline = asyncio.get_running_loop().time() + timeout
    while not condition():
        assert asyncio.get_running_loop().time() < deadline, "condition not met in time"
        await asyncio.sleep(0.01)


def test_live_frames_carry_points_without_labels_or_empty_fields():
    points = [
        point("cpu", 1.0, T0),
        point("mem", 2.0, T0, skill="nav", component="planner"),
        point("fps", 3.0, T0, skill=None, component="camera", labels={"core": "0"}),
    ]
    assert json.loads(metrics_data_json("r1", points)) == {
        "robot": "r1",
        "metrics": [
            {"name": "cpu", "value": 1.0, "ts": T0},
            {"name": "mem", "value": 2.0, "ts": T0, "skill": "nav", "component": "planner"},
            {"name": "fps", "value": 3.0, "ts": T0, "component": "camera"},
        ],
    }


class Rollback(Exception):
    pass


def change_robot(frame: dict, *, fail: bool) -> None:
    with transaction.atomic():
        publish_on_commit("r1", frame)
        if fail:
            raise Rollback


async def test_publish_on_commit_sends_nothing_when_the_transaction_rolls_back(redis_layer):
    layer = get_channel_layer()
    channel = await layer.new_channel()
    await layer.group_add(LIVE_GROUP, channel)
    try:
        with pytest.raises(Rollback):
            await sync_to_async(change_robot)({"status": "rolled back"}, fail=True)
        await sync_to_async(change_robot)({"status": "committed"}, fail=False)

        message = await asyncio.wait_for(layer.receive(channel), timeout=3)

        assert message == {"type": "live.event", "robot": "r1", "frame": {"status": "committed"}}
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(layer.receive(channel), timeout=0.5)
    finally:
        await layer.group_discard(LIVE_GROUP, channel)
        await layer.close_pools()


def test_prune_metrics_command_deletes_old_points(robots):
    now = timezone.now()
    Metric.objects.bulk_create(
        [Metric(robot_id="r1", name="cpu", value=i, ts=now - timedelta(days=i)) for i in range(10)]
    )
    out = io.StringIO()

    call_command("prune_metrics", "--older-than", "4.5", stdout=out)

    assert out.getvalue().strip() == "Deleted 5 metric points."
    assert sorted(Metric.objects.values_list("value", flat=True)) == [0, 1, 2, 3, 4]


async def test_the_next_batch_is_written_while_the_event_loop_is_still_busy(robots, make_writer, monkeypatch):
    writer = make_writer(flush_rows=10, flush_interval=60)
    first = writer.add("r1", [point("cpu", float(i), T0 + i) for i in range(10)])
    sink = writer._sink
    write = sink.write
    calls: list[int] = []

    def slow_first_write(entries):
        calls.append(len(entries))
        if len(calls) == 1:
            time.sleep(0.5)  # a slow COPY, while the robots' next frames arrive
        return write(entries)

    monkeypatch.setattr(sink, "write", slow_first_write)
    await asyncio.sleep(0.1)  # the first batch is being written
    second = writer.add("r2", [point("cpu", float(i), T0 + i) for i in range(10)])
    await asyncio.sleep(0.1)  # the second is cut and handed to the thread behind it
    # The loop is busy (a backlog of frames) while the first batch commits: the thread goes on to
    # the second without waiting for the loop to take the first one's result.
    time.sleep(1.0)  # noqa: ASYNC251 - the point: the loop blocked, as under a backlog
    with psycopg.connect(conninfo_from_settings()) as conn:
        committed = conn.execute("SELECT count(*) FROM monitoring_metric").fetchone()[0]
    assert committed == 20
    await asyncio.wait_for(asyncio.gather(first, second), timeout=5)
    assert calls == [1, 1] and writer.rows_written == 20


async def test_an_idle_writer_leaves_the_event_loop_free(robots, make_writer):
    writer = make_writer(flush_interval=0.05)
    await asyncio.wait_for(writer.add("r1", [point("cpu", 1.0, T0)]), timeout=5)
    used = time.thread_time()
    await asyncio.wait_for(asyncio.sleep(0.5), timeout=5)
    # Ten intervals with nothing to write: a few wakeups, not a loop spinning on the CPU.
    assert time.thread_time() - used < 0.1
