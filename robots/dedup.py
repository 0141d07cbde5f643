"""The window of frame ids already applied per robot, kept where a new consumer finds it."""

from __future__ import annotations

import asyncio
from collections import defaultdict

from django.conf import settings

from bridgeos_cloud.loopowned import loop_object

# Only frames in flight when a link dropped are ever resent, so a short window is plenty.
WINDOW = 1_000
FLUSH_INTERVAL = 2.0
KEY = "bridgeos:applied:{}"
KEEP_SECONDS = 7 * 24 * 3600


class AppliedIds:
    """Remember applied frame ids per robot, in Redis when configured, else in this process.

    Ids are saved in one pipeline for all robots every two seconds, rather than a round trip
    per frame; a consumer that starts after a crash loses at most those last seconds of ids.
    """

    def __init__(self, redis_url: str | None) -> None:
        self._redis = None
        if redis_url:
            import redis.asyncio as aioredis

            # A blocking pool: a connect storm's thousand loads wait for a connection instead of failing.
            pool = aioredis.BlockingConnectionPool.from_url(redis_url, max_connections=100, timeout=30)
            self._redis = aioredis.Redis.from_pool(pool)
        self._local: dict[str, list[str]] = defaultdict(list)
        self._unsaved: dict[str, list[str]] = defaultdict(list)
        self._flusher: asyncio.TimerHandle | None = None
        self._tasks: set[asyncio.Task] = set()
        self._loads: list[tuple[str, asyncio.Future[list[str]]]] = []
        # Frames accepted but not yet applied (metrics wait for their commit), by robot and id:
        # a copy resent over a new connection meanwhile must wait for the first, not be applied twice.
        self._in_flight: dict[tuple[str, str], asyncio.Future] = {}
        # The latest write of ids to Redis; each write ends after the one before it, so awaiting
        # the latest means every id handed to a write so far is saved.
        self._saving: asyncio.Future | None = None

    def hold(self, robot_id: str, frame_id: str, applied: asyncio.Future) -> None:
        """Note a frame being applied until ``applied`` completes.

        Only metrics frames are held, and their ids are not saved here once applied: the frame's
        row in PostgreSQL, committed with its points, is where any process finds it (ingest claims
        it), so a resend is still stored once. Saving them too cost a third of a Redis round trip
        per frame, a tenth of daphne's CPU under 600 metric frames a second (py-spy).
        """
        key = (robot_id, frame_id)
        self._in_flight[key] = applied
        applied.add_done_callback(lambda _: self._in_flight.pop(key, None))

    def in_flight(self, robot_id: str, frame_id: str) -> asyncio.Future | None:
        """Return the pending application of a frame another connection accepted, if any."""
        return self._in_flight.get((robot_id, frame_id))

    async def load(self, robot_id: str) -> list[str]:
        """Return the robot's applied ids, oldest first."""
        await self.flush()
        if self._redis is None:
            return list(self._local[robot_id])
        # The loads asked for in one turn of the loop share one pipeline: a connect storm's
        # thousands of robots cost a few round trips to Redis, not one each.
        future: asyncio.Future[list[str]] = asyncio.get_running_loop().create_future()
        self._loads.append((robot_id, future))
        if len(self._loads) == 1:
            task = asyncio.get_running_loop().create_task(self._load_queued())
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)
        return await future

    async def _load_queued(self) -> None:
        await asyncio.sleep(0)  # let the rest of this turn's loads join
        loads, self._loads = self._loads, []
        assert self._redis is not None
        try:
            async with self._redis.pipeline(transaction=False) as pipe:
                for robot_id, _ in loads:
                    pipe.lrange(KEY.format(robot_id), 0, WINDOW - 1)
                answers = await pipe.execute()
        except Exception as exc:
            for _, future in loads:
                if not future.done():
                    future.set_exception(exc)
            return
        for (_, future), newest_first in zip(loads, answers, strict=True):
            if not future.done():
                future.set_result([raw.decode() for raw in reversed(newest_first)])

    def add(self, robot_id: str, frame_id: str) -> None:
        """Note that a frame was applied; it is saved within two seconds."""
        self._unsaved[robot_id].append(frame_id)
        if self._flusher is None:
            self._flusher = asyncio.get_running_loop().call_later(FLUSH_INTERVAL, self._flush_soon)

    def _flush_soon(self) -> None:
        self._flusher = None
        task = asyncio.get_running_loop().create_task(self.flush())
        self._tasks.add(task)
        task.add_done_callback(self._flushed)

    def _flushed(self, task: asyncio.Task) -> None:
        self._tasks.discard(task)
        # A failed background write is retried by the next one; its ids are queued again.
        if not task.cancelled():
            task.exception()

    async def close(self) -> None:
        """Save every unsaved id and let go of Redis (at shutdown)."""
        if self._flusher is not None:
            self._flusher.cancel()
            self._flusher = None
        await self.flush()
        if self._redis is not None:
            await self._redis.aclose()
            self._redis = None

    async def flush(self) -> None:
        """Save every unsaved id now; return once they, and every id being saved already, are saved.

        Frames are acked only after this: a robot that reconnects to another server process and
        resends a frame whose ack it missed finds the frame's id there, so it is not applied twice.
        Frames acked together share one write (their commit is one, too).
        """
        unsaved, self._unsaved = self._unsaved, defaultdict(list)
        if unsaved:
            if self._redis is None:
                for robot_id, ids in unsaved.items():
                    kept = self._local[robot_id]
                    kept.extend(ids)
                    del kept[:-WINDOW]
            else:
                self._saving = asyncio.ensure_future(self._save(unsaved, self._saving))
        saving = self._saving
        if saving is None:
            return
        if saving.done() and not unsaved:
            # Settled before this call: a failure was its own waiters' to hear, and its ids are
            # queued again for the next write, so it must not fail every later flush (Redis is back).
            if not saving.cancelled():
                saving.exception()
            return
        await asyncio.shield(saving)

    async def _save(self, unsaved: dict[str, list[str]], previous: asyncio.Future | None) -> None:
        assert self._redis is not None
        try:
            async with self._redis.pipeline(transaction=False) as pipe:
                for robot_id, ids in unsaved.items():
                    key = KEY.format(robot_id)
                    pipe.lpush(key, *ids)
                    pipe.ltrim(key, 0, WINDOW - 1)
                    pipe.expire(key, KEEP_SECONDS)
                await pipe.execute()
        except Exception:
            # Not saved (Redis gone): queue the ids again, before newer ones, for the next write.
            for robot_id, ids in unsaved.items():
                queued = self._unsaved[robot_id]
                queued[:0] = ids
                del queued[:-WINDOW]
            if self._flusher is None:
                self._flusher = asyncio.get_running_loop().call_later(FLUSH_INTERVAL, self._flush_soon)
            raise
        finally:
            if previous is not None:
                # Its failure was its own waiters' to hear; this write only has to end after it.
                await asyncio.wait([previous])


def applied_ids() -> AppliedIds:
    """Return this event loop's store of applied ids; its owner closes it at shutdown."""
    return loop_object("applied ids", lambda: AppliedIds(settings.REDIS_URL))
