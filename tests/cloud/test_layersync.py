"""Synchronous code outside daphne reaches the channel layer through one kept loop per process."""

from __future__ import annotations

import threading

import pytest
from asgiref.sync import SyncToAsync
from channels.layers import get_channel_layer

from bridgeos_cloud import layersync
from bridgeos_cloud.layersync import layer_sync


@pytest.fixture(autouse=True)
def outside_daphne():
    """Run as a Celery worker's thread does: asgiref never clears the loop an earlier test's sync code ran for."""
    for name in ("main_event_loop", "main_event_loop_pid"):
        if hasattr(SyncToAsync.threadlocal, name):
            delattr(SyncToAsync.threadlocal, name)


def test_sync_calls_outside_a_loop_share_one_kept_loop_and_reach_redis():
    layer = get_channel_layer()
    assert layersync._redis_layer(), "the tests run on the Redis channel layer"
    channel = layer_sync(layer.new_channel)()
    send = layer_sync(layer.send)
    loops = []
    for n in range(3):
        send(channel, {"type": "test.message", "n": n})
        loops.append(layersync._loop())
    # Called from another thread too: the same loop, so the same Redis connections.
    worker = threading.Thread(target=lambda: send(channel, {"type": "test.message", "n": 3}))
    worker.start()
    worker.join()
    assert len({id(loop) for loop in loops}) == 1 and layersync._loop() is loops[0]
    received = [layer_sync(layer.receive)(channel)["n"] for _ in range(4)]
    assert received == [0, 1, 2, 3]


async def test_sync_code_inside_a_running_loop_reaches_redis_through_the_kept_loop():
    """As a browser driver's thread or sync code called from async code does: async_to_sync would refuse."""
    layer = get_channel_layer()
    channel = await layer.new_channel()
    layer_sync(layer.send)(channel, {"type": "test.message", "n": 7})
    assert (await layer.receive(channel))["n"] == 7
