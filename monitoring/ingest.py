"""The hot path of metric ingest: a per-process batched writer that acks only committed rows.

Consumers hand every `metrics` frame to `get_writer().add()` and ack the robot once the
returned future resolves, so a frame is acknowledged only after its rows are committed and
nothing is lost if the process dies. Rows are buffered and written in batches: with COPY on
PostgreSQL (tens of thousands of rows per second), with `bulk_create` elsewhere, in a thread of
the writer's own, so a busy event loop delays when a batch starts but never its round trips.

A frame's id is committed with its rows (`IngestedFrame`), so a copy the robot resends because
the ack never reached it (daphne killed, Redis or PostgreSQL restarted between commit and ack)
is recognised in the same transaction and stored once.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING

import psycopg
from django.db import InterfaceError, OperationalError, connections

from bridgeos_cloud.loopowned import loop_object

from . import prometheus
from .sinks import Entry, OrmSink, PostgresSink, RobotsDeleted, Sink

if TYPE_CHECKING:
    from bridgeos_agent.protocol import MetricPoint

logger = logging.getLogger(__name__)

# Errors after which a fresh connection may succeed; anything else is refused data.
_CONNECTION_ERRORS = (psycopg.OperationalError, psycopg.InterfaceError, OperationalError, InterfaceError, OSError)


class WriterOverloaded(Exception):
    """The writer holds too many uncommitted rows; the robot should resend later."""


# --------------------------------------------------------------------------- the writer


class MetricWriter:
    """Buffer metric points and write them in batches, resolving each caller once committed."""

    def __init__(
        self,
        *,
        flush_rows: int = 5000,
        flush_interval: float = 0.25,
        max_pending_rows: int = 500_000,
        using: str = "default",
    ) -> None:
        self.flush_rows = flush_rows
        self.flush_interval = flush_interval
        self.max_pending_rows = max_pending_rows
        self.using = using
        # Observability: read them from a status view or a debugger.
        self.rows_written = 0
        self.rows_dropped = 0
        self.rows_already_stored = 0  # rows of resent frames found committed before: not stored twice
        self.batches = 0
        self.last_flush_seconds = 0.0
        self.pending_rows = 0  # added, neither committed nor failed yet
        self._buffer: list[Entry] = []
        self._buffered_rows = 0
        self._buffered_since = 0.0  # monotonic time the oldest buffered frame arrived
        self._sink: Sink | None = None
        # Every call on the sink runs here, one at a time, so it holds one database connection.
        self._thread = ThreadPoolExecutor(max_workers=1, thread_name_prefix="metric-writer")
        self._lock = threading.Lock()
        self._wake = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._closing = False

    def add(self, robot_id: str, points: Sequence[MetricPoint], frame_id: str | None = None) -> asyncio.Future[None]:
        """Queue the points of one robot; the future resolves once they are committed (a known frame id: at once)."""
        future: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        if not points:
            future.set_result(None)
            return future
        if self._closing:
            raise RuntimeError("the metric writer is closed")
        if self.pending_rows >= self.max_pending_rows:
            future.set_exception(WriterOverloaded(f"{self.pending_rows} metric rows wait for the database"))
            return future
        self.start()
        try:
            payload = self._sink.prepare(robot_id, points)  # type: ignore[union-attr]
        except (ValueError, TypeError, OverflowError, AttributeError) as exc:
            # A point that cannot be formatted fails only its own frame, never a whole batch.
            future.set_exception(exc)
            return future
        rows = len(points)
        with self._lock:  # the writer's thread cuts batches from the buffer too
            if not self._buffer:
                self._buffered_since = time.monotonic()
            self._buffer.append(Entry(robot_id, payload, rows, future, frame_id))
            self._buffered_rows += rows
        self.pending_rows += rows
        if self._buffered_rows >= self.flush_rows:
            self._wake.set()
        return future

    @property
    def closed(self) -> bool:
        """Tell whether close() was called."""
        return self._closing

    def start(self) -> None:
        """Start the background flusher on the running loop, if not yet started."""
        if self._task is not None:
            return
        if self._sink is None:
            vendor = connections[self.using].vendor
            self._sink = PostgresSink(self.using) if vendor == "postgresql" else OrmSink(self.using)
        self._task = asyncio.get_running_loop().create_task(self._run(), name="metric-writer")

    async def close(self) -> None:
        """Flush every buffered point, then stop the flusher and drop the connection."""
        self._closing = True
        self._wake.set()
        if self._task is not None:
            await self._task
            self._task = None
        if self._sink is not None:
            await asyncio.get_running_loop().run_in_executor(self._thread, self._sink.reset)
            self._sink = None
        self._thread.shutdown(wait=False)

    async def flush(self) -> None:
        """Write every point buffered so far and return once it is committed or failed."""
        with self._lock:
            futures = [entry.future for entry in self._buffer]
        if futures:
            self._wake.set()
            await asyncio.gather(*futures, return_exceptions=True)

    async def _run(self) -> None:
        loop = asyncio.get_running_loop()
        last_started = loop.time()
        while True:
            # Flushes start every interval, not an interval after the last one ended: a slow
            # COPY must not add its own duration to every point's wait.
            wait = self.flush_interval - (loop.time() - last_started)
            if wait > 0 and not self._wake.is_set() and not self._closing:
                try:
                    async with asyncio.timeout(wait):
                        await self._wake.wait()
                except TimeoutError:
                    pass
            self._wake.clear()
            last_started = loop.time()
            if self._buffer:
                prometheus.INGEST_PENDING_ROWS.set(self.pending_rows)
                # The thread writes batch after batch while there is enough for one; each is settled
                # on the loop as it commits. It returns once the buffer is nearly empty.
                await loop.run_in_executor(self._thread, self._drain, loop)
            elif self._closing:
                return

    def _take(self) -> tuple[list[Entry], int, float]:
        """Cut the buffer into a batch: its entries, their rows and when the oldest arrived."""
        with self._lock:
            entries, self._buffer = self._buffer, []
            rows, self._buffered_rows = self._buffered_rows, 0
            return entries, rows, self._buffered_since

    def _drain(self, loop: asyncio.AbstractEventLoop) -> None:
        """Write buffered batches back to back, handing each result to the loop (in the writer's thread)."""
        # The thread cuts the next batch itself: under 30,000 points/s from 10,000 robots the loop's
        # turns grew to seconds, and a thread that waited for the loop to hand it the next batch
        # stood idle as long, stored 25,000 points/s at most and fell behind (benchmarks/tenk.py).
        while True:
            entries, rows, since = self._take()
            if not entries:
                return
            started = time.perf_counter()
            try:
                outcome: tuple[list[Entry], dict[Entry, BaseException]] | BaseException = self._write(entries)
            except Exception as exc:
                outcome = exc
            self.last_flush_seconds = time.perf_counter() - started
            loop.call_soon_threadsafe(self._settle, entries, rows, since, outcome)
            with self._lock:
                enough = self._buffered_rows >= self.flush_rows or (
                    self._buffer and time.monotonic() - self._buffered_since >= self.flush_interval
                )
            if not enough and not self._closing:
                return  # the loop starts the next one at its interval

    def _settle(
        self,
        entries: list[Entry],
        rows: int,
        since: float,
        outcome: tuple[list[Entry], dict[Entry, BaseException]] | BaseException,
    ) -> None:
        """Resolve the callers of a written batch, or fail them (on the loop)."""
        self.pending_rows -= rows
        prometheus.INGEST_PENDING_ROWS.set(self.pending_rows)
        if isinstance(outcome, BaseException):
            logger.warning("Writing %d metric rows failed: %r", rows, outcome)
            prometheus.copy_failed()
            self._fail(entries, outcome)
            return
        written, failed = outcome
        self.batches += 1
        self.rows_written += sum(entry.rows for entry in written)
        prometheus.batch_written(sum(entry.rows for entry in written), since)
        if failed:
            prometheus.copy_failed(len(failed))
        for entry, error in failed.items():
            if not entry.future.done():
                entry.future.set_exception(error)
        # Dropped rows of deleted robots resolve too: there is nobody left to resend them to.
        for entry in entries:
            if not entry.future.done():
                entry.future.set_result(None)

    def _fail(self, entries: list[Entry], exc: BaseException) -> None:
        for entry in entries:
            if not entry.future.done():
                entry.future.set_exception(exc)

    def _write(self, entries: list[Entry]) -> tuple[list[Entry], dict[Entry, BaseException]]:
        """Write a batch and return what was written and which frames failed, retrying once (in the writer's thread)."""
        sink = self._sink
        assert sink is not None
        retried = False
        while True:
            try:
                self.rows_already_stored += sink.write(entries)
                return entries, {}
            except Exception as exc:
                if isinstance(exc, RobotsDeleted):
                    kept = self._without_deleted_robots(entries, sink)
                    if len(kept) < len(entries):
                        entries = kept
                        continue
                if retried:
                    raise
                retried = True
                logger.warning("Writing %d metric frames failed, retrying once: %r", len(entries), exc)
                if not isinstance(exc, _CONNECTION_ERRORS):
                    break
                sink.reset()
        # The data itself was refused: write frame by frame, so one bad frame fails alone.
        errors = sink.write_each(entries)
        failed = {entry: error for entry, error in zip(entries, errors, strict=True) if error is not None}
        return [entry for entry in entries if entry not in failed], failed

    def _without_deleted_robots(self, entries: list[Entry], sink: Sink) -> list[Entry]:
        """Return the entries of robots that still exist, logging the dropped ones once."""
        robot_ids = {entry.robot_id for entry in entries}
        missing = robot_ids - sink.existing_robots(robot_ids)
        if missing:
            dropped = sum(entry.rows for entry in entries if entry.robot_id in missing)
            self.rows_dropped += dropped
            names = ", ".join(sorted(missing)[:10]) + (f" and {len(missing) - 10} more" if len(missing) > 10 else "")
            logger.warning("Dropped %d metric rows of deleted robots: %s", dropped, names)
        return [entry for entry in entries if entry.robot_id not in missing]


def _started_writer() -> MetricWriter:
    writer = MetricWriter()
    writer.start()
    return writer


def get_writer() -> MetricWriter:
    """Return this event loop's metric writer, started on first use; its owner closes it at shutdown."""
    return loop_object("metric writer", _started_writer, usable=lambda writer: not writer.closed)
