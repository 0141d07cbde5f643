"""The channel layer: channels_redis's, with a receive that loses no message when its reader is cancelled.

A process's consumers share one Redis queue, and whichever consumer holds the layer's receive
lock pops it (BZPOPMIN) for all of them. When that consumer's connection closes, channels cancels
its receive mid-pop: a message Redis had already popped for another consumer was dropped
(django/channels_redis#366). Seen as a client that never heard of a skill_status its robot had
reported while another robot disconnected; 1 message in 17,600 under steady connect and disconnect
churn. Here a cancelled reader finishes its pop first, still the reader, and hands what it popped to the
consumers it was for, as it would have; then it ends.
"""

from __future__ import annotations

import asyncio
from typing import Any

from channels_redis.core import RedisChannelLayer

__all__ = ["ChannelLayer"]


class ChannelLayer(RedisChannelLayer):
    """channels_redis's layer, whose process-wide pop is finished even when the consumer running it is cancelled."""

    async def receive_single(self, channel: str) -> Any:
        """Pop one message off a channel; for a process's channels, finish the pop even if cancelled."""
        if not channel.endswith("!"):
            return await super().receive_single(channel)  # a named channel: a cancelled pop is its own loss
        pop = asyncio.ensure_future(super().receive_single(channel))
        cancelled = False
        while not pop.done():
            try:
                await asyncio.shield(pop)
            except asyncio.CancelledError:
                if pop.cancelled():
                    raise  # the pop itself was cancelled (its loop closing): nothing was popped
                # Finished first, still holding the receive lock (at most the pop's 5 s timeout), so the
                # other consumers go on waiting on their buffers and find what it brings in order.
                cancelled = True
            except Exception:
                break
        if not cancelled:
            return pop.result()
        if pop.exception() is None:
            message_channel, message = pop.result()
            for each in message_channel if isinstance(message_channel, list) else [message_channel]:
                self.receive_buffer[each].put_nowait(message)
        raise asyncio.CancelledError
