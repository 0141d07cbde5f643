"""The channel layer: channels_redis's, with a receive that loses no message when its reader is cancelled.

A process's consumers share one Redis queue, and whichever consumer holds the layer's receive
lock pops it (BZPOPMIN) for all of them. When that consumer's connection closes, channels cancels
its receive mid-pop: a message Redis had already popped for another consumer was dropped
(django/channels_redis#366). Seen as a client that never heard of a skill_status its robot had
reported while another robot disconnected; 5 messages in ~62,700 under connect and disconnect
churn. Here a cancelled reader finishes its one pop in flight (at most the pop's 5 s timeout), so
what it popped reaches channels_redis's backup queue, which the next reader puts back before
popping: delivered, in order.
"""

from __future__ import annotations

import asyncio
from typing import Any

from channels_redis.core import RedisChannelLayer

__all__ = ["ChannelLayer"]


class ChannelLayer(RedisChannelLayer):
    """channels_redis's layer, whose pop of a process's queue is finished even when its consumer is cancelled."""

    async def _brpop_with_clean(self, index: int, channel: str, timeout: int) -> Any:
        """Pop one message (or time out) into channels_redis's backup queue; if cancelled, finish first."""
        pop = asyncio.ensure_future(super()._brpop_with_clean(index, channel, timeout))
        cancelled = False
        while not pop.done():
            try:
                await asyncio.shield(pop)
            except asyncio.CancelledError:
                if pop.cancelled():
                    raise  # the pop itself was cancelled (its loop closing)
                cancelled = True  # again while waiting too (daphne re-cancels a closing consumer every second)
            except Exception:
                break
        if cancelled:
            # What it popped waits in the backup queue, which the next reader's pop puts back first.
            raise asyncio.CancelledError
        return pop.result()
