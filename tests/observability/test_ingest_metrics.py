"""The ingest and live-feed families, after real writes to PostgreSQL and real channel-layer failures."""

from __future__ import annotations

import asyncio

import pytest
from asgiref.sync import sync_to_async
from channels_redis.core import RedisChannelLayer

from bridgeos_agent.protocol import MetricPoint
from monitoring import prometheus
from monitoring.live import LIVE_GROUP, LiveFeed
from tests.cloud.test_ingest import T0, close_thread_connections, make_writer, point, robots  # noqa: F401  (fixtures)

from .promutil import value

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio]


async def here() -> str:
    """Return what /metrics would serve now (this process's values included)."""
    return (await sync_to_async(prometheus.exposition)()).decode()


async def test_batches_rows_lag_and_refused_frames_are_counted(robots, make_writer):  # noqa: F811
    before = await here()
    writer = make_writer(flush_interval=60)
    good = writer.add("r1", [point("cpu", 1.0, T0), point("cpu", 2.0, T0 + 1)])
    # Built without validation: a name longer than the column allows, so PostgreSQL refuses its frame.
    bad = writer.add("r2", [MetricPoint(name="x" * 200, value=1.0, ts=T0)])
    await asyncio.sleep(0.05)
    await writer.flush()
    await asyncio.gather(good, bad, return_exceptions=True)
    after = await here()

    assert value(after, "bridgeos_ingest_rows_written_total") - value(before, "bridgeos_ingest_rows_written_total") == 2
    assert value(after, "bridgeos_ingest_copy_errors_total") - value(before, "bridgeos_ingest_copy_errors_total") == 1
    assert value(after, "bridgeos_ingest_batch_rows_count") - value(before, "bridgeos_ingest_batch_rows_count") == 1
    assert value(after, "bridgeos_ingest_batch_rows_sum") - value(before, "bridgeos_ingest_batch_rows_sum") == 2
    lag = value(after, "bridgeos_ingest_lag_seconds_sum") - value(before, "bridgeos_ingest_lag_seconds_sum")
    assert lag >= 0.05  # the oldest frame waited at least the sleep before its batch committed
    assert value(after, "bridgeos_ingest_pending_rows") == 0


async def test_live_feed_messages_and_drops_are_counted():
    points = [point("cpu", 0.5, T0)]
    before = await here()
    # A real Redis layer on a port nobody listens on: every send fails, and the values are dropped.
    broken = LiveFeed(interval=0.02, layer=RedisChannelLayer(hosts=["redis://127.0.0.1:1/0"]))
    broken.add_metrics("r1", points)
    for _ in range(200):
        if value(await here(), "bridgeos_live_drops_total") > value(before, "bridgeos_live_drops_total"):
            break
        await asyncio.sleep(0.05)
    broken._task.cancel()
    assert value(await here(), "bridgeos_live_drops_total") - value(before, "bridgeos_live_drops_total") >= 1

    from django.conf import settings

    layer = RedisChannelLayer(hosts=[settings.REDIS_URL])
    watcher = await layer.new_channel()  # the feed sends only while someone watches
    await layer.group_add(LIVE_GROUP, watcher)
    working = LiveFeed(interval=60, layer=layer)
    working.add_metrics("r1", points)
    await working.close()
    await layer.group_discard(LIVE_GROUP, watcher)
    assert value(await here(), "bridgeos_live_messages_total") - value(before, "bridgeos_live_messages_total") == 1
