"""The consumers (and relays) of this process by channel name, reached without the channel layer.

A frame between a robot and a client served by the same process, a command to a robot and the
robot's reply to the relay that sent it: each skips Redis when both ends are here. Anything whose
other end is elsewhere, or that is sent from another event loop (a Celery worker, a thread's own
loop), goes through the channel layer as before.
"""

from __future__ import annotations

import asyncio
import weakref
from typing import Any

from channels.exceptions import ChannelFull
from channels.layers import get_channel_layer

_local: weakref.WeakValueDictionary[str, Any] = weakref.WeakValueDictionary()
# The loop each runs on (daphne's one loop, for consumers): only code on that loop may call it directly.
_loops: weakref.WeakKeyDictionary[Any, asyncio.AbstractEventLoop] = weakref.WeakKeyDictionary()


def register_local(consumer: Any) -> None:
    """Let messages for this consumer's channel reach it directly from this process."""
    _loops[consumer] = asyncio.get_running_loop()
    _local[consumer.channel_name] = consumer


def unregister_local(consumer: Any) -> None:
    """Stop handing messages for this consumer's channel to it directly."""
    if _local.get(consumer.channel_name) is consumer:
        del _local[consumer.channel_name]


def local_consumer(channel: str) -> Any | None:
    """Return the consumer of a channel if it is in this process and on the running loop."""
    consumer = _local.get(channel)
    if consumer is None or _loops.get(consumer) is not asyncio.get_running_loop():
        return None
    return consumer


async def deliver(channel: str, message: dict[str, Any]) -> bool:
    """Hand a message to a consumer (in this process if it is here); False if it was dropped."""
    consumer = local_consumer(channel)
    if consumer is not None:
        await consumer.dispatch(message)
        return True
    try:
        await get_channel_layer().send(channel, message)
    except ChannelFull:
        return False
    return True
