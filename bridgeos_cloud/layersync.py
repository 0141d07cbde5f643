"""Call the channel layer from synchronous code outside daphne (Celery workers, commands) on one kept loop.

``async_to_sync`` there starts a thread, an event loop and a Redis connection for every call: five
of them after a cloud copy starts cost the robot's move a fifth of a second on a loaded machine.
Here each process keeps one loop in a thread of its own, whose Redis connections stay open. Under
daphne (a sync view or a database thread of a consumer) ``async_to_sync`` already hands the call to
daphne's own loop, and the in-memory layer's queues belong to the loop they were made on: both keep
going through ``async_to_sync``.
"""

from __future__ import annotations

import asyncio
import os
import threading
from collections.abc import Callable, Coroutine
from typing import Any, ParamSpec, TypeVar

from asgiref.sync import SyncToAsync, async_to_sync
from channels.layers import get_channel_layer
from channels_redis.core import RedisChannelLayer

__all__ = ["layer_sync"]

P = ParamSpec("P")
R = TypeVar("R")

_lock = threading.Lock()
_kept: tuple[int, asyncio.AbstractEventLoop] | None = None  # (pid, loop): a forked worker starts its own


def layer_sync(function: Callable[P, Coroutine[Any, Any, R]]) -> Callable[P, R]:
    """Return a synchronous caller of an async function that talks to the channel layer."""

    def call(*args: P.args, **kwargs: P.kwargs) -> R:
        if _handed_to_daphne() or not _redis_layer():
            return async_to_sync(function)(*args, **kwargs)
        # Also where a loop runs in this very thread (sync code called from async code, a test's
        # browser driver): async_to_sync refuses there, and the kept loop's thread is not this one.
        return asyncio.run_coroutine_threadsafe(function(*args, **kwargs), _loop()).result()

    return call


def _handed_to_daphne() -> bool:
    """Tell whether daphne's loop owns this call (a sync view, or a consumer's database thread, via asgiref)."""
    return getattr(SyncToAsync.threadlocal, "main_event_loop", None) is not None


def _redis_layer() -> bool:
    layer = get_channel_layer()
    return isinstance(layer, RedisChannelLayer)


def _loop() -> asyncio.AbstractEventLoop:
    """Return this process's kept loop, started on first use."""
    global _kept
    with _lock:
        if _kept is None or _kept[0] != os.getpid():
            loop = asyncio.new_event_loop()
            threading.Thread(target=loop.run_forever, name="channel-layer", daemon=True).start()
            _kept = (os.getpid(), loop)
        return _kept[1]
