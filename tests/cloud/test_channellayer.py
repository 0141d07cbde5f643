"""The channel layer loses no message when the consumer popping for its process is cancelled mid-pop."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import AsyncIterator

import pytest
import redis
from channels_redis.core import RedisChannelLayer

from bridgeos_cloud.channellayer import ChannelLayer

pytestmark = pytest.mark.asyncio

TEST_REDIS_URL = "redis://127.0.0.1:6379/13"


@pytest.fixture
async def sender() -> AsyncIterator[RedisChannelLayer]:
    """Return another process's layer, which sends; the test database of Redis is emptied after."""
    layer = RedisChannelLayer(hosts=[TEST_REDIS_URL])
    yield layer
    await layer.flush()


def send_from_elsewhere(sender: RedisChannelLayer, channel: str, message: dict) -> None:
    """Send as another process does, blocking this loop meanwhile: its consumers do not run until it returns."""
    thread = threading.Thread(target=lambda: asyncio.run(sender.send(channel, message)))
    thread.start()
    thread.join()


def wait_until_popped(layer: RedisChannelLayer, channel: str) -> None:
    """Block this loop until Redis has popped the process's queue (the reply is on its way to the reader)."""
    key = layer.prefix + layer.non_local_name(channel)
    with redis.Redis.from_url(TEST_REDIS_URL) as client:
        deadline = time.monotonic() + 5
        while client.zcard(key) and time.monotonic() < deadline:
            time.sleep(0.001)
        assert client.zcard(key) == 0, "the reader never popped"


@pytest.mark.parametrize("layer_class", [ChannelLayer, RedisChannelLayer], ids=["ours", "channels_redis"])
async def test_a_message_popped_as_its_reader_is_cancelled_reaches_the_consumer_it_is_for(
    layer_class: type[RedisChannelLayer], sender: RedisChannelLayer
) -> None:
    layer = layer_class(hosts=[TEST_REDIS_URL])
    leaving, staying = await layer.new_channel(), await layer.new_channel()
    reader = asyncio.ensure_future(layer.receive(leaving))
    await asyncio.sleep(0.05)  # the first receive takes the lock and pops for the whole process
    waiting = asyncio.ensure_future(layer.receive(staying))
    await asyncio.sleep(0.05)

    send_from_elsewhere(sender, staying, {"type": "live.event", "n": 1})
    wait_until_popped(layer, staying)
    reader.cancel()  # its connection closed: channels cancels its receive, with the reply in flight

    (ended,) = await asyncio.gather(reader, return_exceptions=True)
    if layer_class is ChannelLayer:
        assert isinstance(ended, asyncio.CancelledError)
        assert await asyncio.wait_for(waiting, 7) == {"type": "live.event", "n": 1}
    else:
        # Why the layer exists: channels_redis drops the message (django/channels_redis#366). The
        # staying consumer waits in vain, or its own receive fails on the reader's abandoned reply.
        (outcome,) = await asyncio.gather(asyncio.wait_for(waiting, 7), return_exceptions=True)
        assert isinstance(outcome, (TimeoutError, redis.RedisError)), outcome


async def test_the_other_consumers_go_on_receiving_in_order_after_the_reader_leaves(sender: RedisChannelLayer) -> None:
    layer = ChannelLayer(hosts=[TEST_REDIS_URL])
    leaving, staying = await layer.new_channel(), await layer.new_channel()
    reader = asyncio.ensure_future(layer.receive(leaving))
    await asyncio.sleep(0.05)
    received: list[int] = []

    async def consume() -> None:
        while len(received) < 20:
            received.append((await layer.receive(staying))["n"])

    consumer = asyncio.ensure_future(consume())
    await asyncio.sleep(0.05)
    for n in range(10):
        await sender.send(staying, {"type": "live.event", "n": n})
    reader.cancel()
    for n in range(10, 20):
        await sender.send(staying, {"type": "live.event", "n": n})
    await asyncio.wait_for(consumer, 10)
    assert received == list(range(20))
    with pytest.raises(asyncio.CancelledError):
        await reader


async def test_a_cancelled_reader_with_nothing_to_pop_ends_within_its_pops_timeout(sender: RedisChannelLayer) -> None:
    layer = ChannelLayer(hosts=[TEST_REDIS_URL])
    reader = asyncio.ensure_future(layer.receive(await layer.new_channel()))
    await asyncio.sleep(0.05)
    started = time.monotonic()
    for _ in range(3):  # daphne cancels a closing consumer again every second
        reader.cancel()
        await asyncio.sleep(0.2)
    (ended,) = await asyncio.gather(asyncio.wait_for(reader, layer.brpop_timeout + 2), return_exceptions=True)
    assert isinstance(ended, asyncio.CancelledError)
    assert time.monotonic() - started <= layer.brpop_timeout + 0.5
