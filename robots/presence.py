"""Which server processes are alive, so robots held by one that died without a goodbye go offline.

Each daphne process keeps a Redis key with a short TTL alive while it runs and lists itself in a
set of processes. A robot's row names the consumer channel holding it, and channels-redis names
channels after their process, so the robots of a process whose key expired are found by their
channel. Every live process sweeps: the first to see a dead process marks its robots disconnected.
"""

from __future__ import annotations

import asyncio
import hashlib
import logging
import weakref
from typing import Any

from channels.db import database_sync_to_async
from channels.layers import get_channel_layer
from django.conf import settings
from django.db import connections

from bridgeos_agent.logonce import LogOnce
from bridgeos_cloud.loopowned import loop_object

from . import services

log = logging.getLogger(__name__)

PROCESSES_KEY = "bridgeos:processes:{}"
PROCESS_KEY = "bridgeos:process:{}"
DEAD_PROCESS_REASON = "its cloud process stopped answering"


def cloud_namespace() -> str:
    """Return what tells this cloud's processes apart from other clouds' sharing the Redis: its database."""
    db = connections["default"].settings_dict
    identity = settings.BRIDGEOS["CLOUD_ID"] or f"{db.get('HOST') or ''}:{db.get('PORT') or ''}/{db.get('NAME')}"
    return hashlib.sha256(identity.encode()).hexdigest()[:12]


def process_of(channel: str) -> str:
    """Return the server process a consumer's channel belongs to (channels-redis prefixes them per process)."""
    return channel.partition("!")[0]


class Presence:
    """This process's heartbeat in Redis, and the sweep that expires the connections of dead processes."""

    def __init__(self, redis_url: str, process: str) -> None:
        import redis.asyncio as aioredis

        self.process = process
        # Only this cloud's processes: a sweep finds the robots of dead ones in this cloud's database only.
        self.processes_key = PROCESSES_KEY.format(cloud_namespace())
        self.heartbeat_s = settings.BRIDGEOS["PROCESS_HEARTBEAT_S"]
        self.ttl_s = settings.BRIDGEOS["PROCESS_TTL_S"]
        self._redis = aioredis.Redis.from_url(redis_url, socket_timeout=5)
        # The consumers holding robots here, to close those a sweep expired while this process stalled.
        self.consumers: weakref.WeakSet[Any] = weakref.WeakSet()
        self._joined = asyncio.ensure_future(self._beat())
        self._loop_task: asyncio.Task | None = None
        self.closed = False

    async def joined(self) -> None:
        """Wait until this process is registered, so no sweep takes its first robots for orphans."""
        await asyncio.shield(self._joined)
        if self._loop_task is None:
            self._loop_task = asyncio.ensure_future(self._run())

    async def _beat(self) -> bool:
        """Refresh this process's key; return whether it was still there."""
        pipe = self._redis.pipeline(transaction=True)
        pipe.set(PROCESS_KEY.format(self.process), "1", ex=max(1, round(self.ttl_s)), get=True)
        pipe.sadd(self.processes_key, self.process)
        previous, _ = await pipe.execute()
        return previous is not None

    async def _run(self) -> None:
        failures = LogOnce(log, "process heartbeat and sweep of dead processes", traceback=True)
        while not self.closed:
            await asyncio.sleep(self.heartbeat_s)
            try:
                if not await self._beat():
                    await self._close_expired()
                await self.sweep()
            except Exception as exc:
                failures.failed(exc)
            else:
                failures.worked()

    async def sweep(self) -> list[str]:
        """Mark disconnected the robots of every listed process whose key expired; return their ids."""
        members = [member.decode() for member in await self._redis.smembers(self.processes_key)]
        others = [member for member in members if member != self.process]
        if not others:
            return []
        pipe = self._redis.pipeline(transaction=False)
        for member in others:
            pipe.exists(PROCESS_KEY.format(member))
        dead = dead_processes(others, await pipe.execute())
        if not dead:
            return []
        dropped = await database_sync_to_async(services.expire_connections)(dead, DEAD_PROCESS_REASON)
        await self._redis.srem(self.processes_key, *dead)
        if dropped:
            log.warning("robots %s were held by a dead cloud process: marked disconnected", ", ".join(dropped))
        return dropped

    async def _close_expired(self) -> None:
        """Close the connections a sweep marked offline while this process stalled: their robots reconnect."""
        held = {consumer.channel_name: consumer for consumer in list(self.consumers) if consumer.robot_id}
        if not held:
            return
        current = await database_sync_to_async(services.current_channels)(list(held))
        for channel, consumer in held.items():
            if channel not in current:
                consumer.spawn(consumer.robot_replaced({}))

    @property
    def usable(self) -> bool:
        """Tell whether this presence still runs (not closed, and its registration did not fail)."""
        failed = self._joined.done() and not self._joined.cancelled() and self._joined.exception() is not None
        return not self.closed and not failed

    async def close(self) -> None:
        """Stop beating; still listed, so another process sweeps up any robot this one failed to mark offline."""
        self.closed = True
        if self._loop_task is not None:
            self._loop_task.cancel()
        await self._redis.delete(PROCESS_KEY.format(self.process))
        await self._redis.aclose()


def dead_processes(listed: list[str], alive: list[int]) -> list[str]:
    """Return the listed processes whose liveness key no longer exists."""
    return [process for process, exists in zip(listed, alive, strict=True) if not exists]


def sweep_dead_processes() -> list[str]:
    """Mark offline the robots of dead processes from outside any server process; return their ids.

    Celery beat runs this, so robots are swept even when no server process is left alive to do it
    (a single daphne that died and did not come back).
    """
    if not settings.REDIS_URL:
        return []
    import redis

    client = redis.Redis.from_url(settings.REDIS_URL, socket_timeout=5)
    try:
        processes_key = PROCESSES_KEY.format(cloud_namespace())
        listed = [member.decode() for member in client.smembers(processes_key)]
        if not listed:
            return []
        pipe = client.pipeline(transaction=False)
        for member in listed:
            pipe.exists(PROCESS_KEY.format(member))
        dead = dead_processes(listed, pipe.execute())
        if not dead:
            return []
        dropped = services.expire_connections(dead, DEAD_PROCESS_REASON)
        client.srem(processes_key, *dead)
    finally:
        client.close()
    if dropped:
        log.warning("robots %s were held by a dead cloud process: marked disconnected", ", ".join(dropped))
    return dropped


def get_presence(channel: str) -> Presence | None:
    """Return this event loop's presence, started on first use; None without Redis (one process only)."""
    if not settings.REDIS_URL:
        return None
    redis_url = settings.REDIS_URL
    return loop_object(
        "process presence", lambda: Presence(redis_url, process_of(channel)), usable=lambda found: found.usable
    )


async def start_presence() -> None:
    """Register this server process at startup, so it sweeps for dead processes before its first robot."""
    try:
        presence = get_presence(await get_channel_layer().new_channel())
        if presence is not None:
            await presence.joined()
    except Exception:
        log.exception("registering this server process failed; it is tried again when a robot connects")
