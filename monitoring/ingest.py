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
import json
import logging
import threading
import time
from collections.abc import Iterable, Sequence
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, Protocol

import psycopg
from django.conf import settings
from django.db import IntegrityError, InterfaceError, OperationalError, connections, transaction

from bridgeos_cloud.loopowned import loop_object

from . import prometheus
from .models import IngestedFrame, Metric

if TYPE_CHECKING:
    from bridgeos_agent.protocol import MetricPoint

logger = logging.getLogger(__name__)

COLUMNS = "robot_id, skill, component, name, value, labels, ts"
# Keys of Django's OPTIONS that are not libpq connection parameters.
_DJANGO_ONLY_OPTIONS = {"pool", "server_side_binding", "isolation_level", "assume_role", "cursor_factory"}
_CACHE_LIMIT = 4096
# Errors after which a fresh connection may succeed; anything else is refused data.
_CONNECTION_ERRORS = (psycopg.OperationalError, psycopg.InterfaceError, OperationalError, InterfaceError, OSError)


class WriterOverloaded(Exception):
    """The writer holds too many uncommitted rows; the robot should resend later."""


# --------------------------------------------------------------------------- COPY text format

# Points arrive in time order, so the formatted second repeats for many rows in a row.
_second_prefixes: dict[int, str] = {}
# Most points carry no labels or the same few label sets; json.dumps costs more than the rest of a row.
_labels_texts: dict[tuple[tuple[str, str], ...], str] = {}
# The (skill, component, name) columns of a series, escaped: a fleet reports the same few series.
_heads: dict[tuple[str | None, str | None, str], str] = {}


def _copy_escape(value: str) -> str:
    """Escape a value for COPY's text format."""
    return value.replace("\\", "\\\\").replace("\t", "\\t").replace("\n", "\\n").replace("\r", "\\r")


def format_ts(ts: float) -> str:
    """Format epoch seconds as timestamptz text, rounded like datetime.fromtimestamp."""
    # The same split and half-even rounding as CPython's datetime, so both paths store the same instant.
    second = int(ts)
    micros = round((ts - second) * 1e6)
    if micros >= 1_000_000:
        micros -= 1_000_000
        second += 1
    elif micros < 0:
        micros += 1_000_000
        second -= 1
    prefix = _second_prefixes.get(second)
    if prefix is None:
        if len(_second_prefixes) >= _CACHE_LIMIT:
            _second_prefixes.clear()
        prefix = _second_prefixes[second] = datetime.fromtimestamp(second, UTC).strftime("%Y-%m-%d %H:%M:%S.")
    return f"{prefix}{micros:06d}+00"


def format_labels(labels: dict[str, str]) -> str:
    """Return labels as JSON escaped for COPY's text format."""
    key = tuple(labels.items())
    text = _labels_texts.get(key)
    if text is None:
        text = json.dumps(labels, ensure_ascii=False, separators=(",", ":"))
        if "\\u0000" in text:
            # jsonb refuses NUL characters, and one bad label must not fail a whole batch.
            clean = {k.replace("\x00", ""): v.replace("\x00", "") for k, v in labels.items()}
            text = json.dumps(clean, ensure_ascii=False, separators=(",", ":"))
        # JSON already escapes control characters, so backslashes are all COPY needs doubled.
        text = text.replace("\\", "\\\\")
        if len(_labels_texts) >= _CACHE_LIMIT:
            _labels_texts.clear()
        _labels_texts[key] = text
    return text


def _row_head(skill: str | None, component: str | None, name: str) -> str:
    """Return the skill, component and name columns of a row, escaped for COPY's text format."""
    head = f"{skill or ''}\t{component or ''}\t{name}"
    # The protocol's slug and name patterns exclude these, so escaping is almost never needed.
    if "\\" in head or "\n" in head or "\r" in head or head.count("\t") != 2:
        head = "\t".join(_copy_escape(part) for part in (skill or "", component or "", name))
    return head


def format_copy_rows(robot_id: str, points: Iterable[MetricPoint]) -> str:
    """Return the points of one robot as lines of COPY text format."""
    # A robot reports the same few series over and over, and the points of one sample share their
    # time: each head and timestamp is formatted once, not once a point (47 us a 15-point frame
    # was more than its parse).
    robot = _copy_escape(robot_id)
    lines = []
    append = lines.append
    last_ts: float | None = None
    ts_text = ""
    for point in points:
        key = (point.get("skill"), point.get("component"), point["name"])
        head = _heads.get(key)
        if head is None:
            if len(_heads) >= _CACHE_LIMIT:
                _heads.clear()
            head = _heads[key] = _row_head(*key)
        ts = point["ts"]
        if ts != last_ts:
            ts_text, last_ts = format_ts(ts), ts
        labels = point.get("labels")
        labels_text = format_labels(labels) if labels else "{}"
        append(f"{robot}\t{head}\t{float(point['value'])!r}\t{labels_text}\t{ts_text}\n")
    return "".join(lines)


# --------------------------------------------------------------------------- sinks


class _Entry:
    """The points of one `add()` call, prepared for the sink, and who waits for them."""

    __slots__ = ("frame_id", "future", "payload", "robot_id", "rows")

    def __init__(
        self, robot_id: str, payload: Any, rows: int, future: asyncio.Future[None], frame_id: str | None = None
    ) -> None:
        self.robot_id = robot_id
        self.frame_id = frame_id
        self.payload = payload
        self.rows = rows
        self.future = future


class _Sink(Protocol):
    """Where batches go; everything but ``prepare`` runs in the writer's thread."""

    def prepare(self, robot_id: str, points: Sequence[MetricPoint]) -> Any: ...

    def write(self, entries: list[_Entry]) -> int: ...

    def write_each(self, entries: list[_Entry]) -> list[BaseException | None]: ...

    def existing_robots(self, robot_ids: set[str]) -> set[str]: ...

    def is_integrity_error(self, exc: BaseException) -> bool: ...

    def reset(self) -> None: ...


def conninfo_from_settings(alias: str = "default") -> str:
    """Build a libpq conninfo string from Django's settings for a database."""
    db = settings.DATABASES[alias]
    params: dict[str, Any] = {
        key: value for key, value in (db.get("OPTIONS") or {}).items() if key not in _DJANGO_ONLY_OPTIONS
    }
    params.update(
        dbname=db.get("NAME") or None,
        user=db.get("USER") or None,
        password=db.get("PASSWORD") or None,
        host=db.get("HOST") or None,
        port=str(db["PORT"]) if db.get("PORT") else None,
    )
    params.setdefault("connect_timeout", 10)
    params.setdefault("application_name", "bridgeos-metric-writer")
    return psycopg.conninfo.make_conninfo(**{k: v for k, v in params.items() if v is not None})


class _PostgresSink:
    """Write batches with COPY over one psycopg connection of its own."""

    # A blocking connection in the writer's thread: psycopg waits for the server without the GIL,
    # and a COPY's round trips no longer queue behind every frame in the event loop. Under 30,000
    # points/s from 10,000 robots the loop's turns grew long enough that the asyncio connection's
    # five or six awaits a batch let pending rows pile up to the writer's limit, and frames were
    # refused as unavailable: 2,500-15,200 points/s stored of 30,000 (benchmarks/tenk.py).

    def __init__(self, alias: str) -> None:
        self.conninfo = conninfo_from_settings(alias)
        self.copy_sql = f"COPY {Metric._meta.db_table} ({COLUMNS}) FROM STDIN"
        self.claim_sql = (
            f"INSERT INTO {IngestedFrame._meta.db_table} (robot_id, frame_id, created) "
            "SELECT robot, frame, now() FROM unnest(%s::text[], %s::text[]) AS f(robot, frame) "
            "ON CONFLICT DO NOTHING RETURNING robot_id, frame_id"
        )
        self.robot_table = Metric._meta.get_field("robot").related_model._meta.db_table
        self.conn: psycopg.Connection[Any] | None = None

    def _connection(self) -> psycopg.Connection[Any]:
        if self.conn is None or self.conn.closed:
            self.conn = psycopg.Connection.connect(self.conninfo, autocommit=False)
        return self.conn

    def prepare(self, robot_id: str, points: Sequence[MetricPoint]) -> str:
        return format_copy_rows(robot_id, points)

    def write(self, entries: list[_Entry]) -> int:
        conn = self._connection()
        with conn.transaction(), conn.cursor() as cursor:
            fresh = self._claim(cursor, entries)
            if fresh:
                with cursor.copy(self.copy_sql) as copy:
                    copy.write("".join([entry.payload for entry in fresh]))
        return sum(entry.rows for entry in entries) - sum(entry.rows for entry in fresh)

    def _claim(self, cursor: psycopg.Cursor[Any], entries: list[_Entry]) -> list[_Entry]:
        """Record the entries' frame ids in this transaction; return the entries not stored before."""
        framed = [entry for entry in entries if entry.frame_id is not None]
        if not framed:
            return entries
        cursor.execute(self.claim_sql, [[entry.robot_id for entry in framed], [entry.frame_id for entry in framed]])
        # A frame already committed (by an earlier connection, or another process) returns no row here.
        claimed = {(robot, frame) for robot, frame in cursor.fetchall()}
        fresh = []
        for entry in entries:
            key = (entry.robot_id, entry.frame_id)
            if entry.frame_id is None:
                fresh.append(entry)
            elif key in claimed:
                claimed.discard(key)  # the same frame twice in one batch is stored once
                fresh.append(entry)
        return fresh

    def write_each(self, entries: list[_Entry]) -> list[BaseException | None]:
        conn = self._connection()
        errors: list[BaseException | None] = []
        with conn.transaction(), conn.cursor() as cursor:
            for entry in entries:
                try:
                    # A savepoint per entry, so one bad frame does not take the others with it.
                    with conn.transaction():
                        if self._claim(cursor, [entry]):
                            with cursor.copy(self.copy_sql) as copy:
                                copy.write(entry.payload)
                except (psycopg.DataError, psycopg.IntegrityError, psycopg.ProgrammingError, UnicodeError) as exc:
                    errors.append(exc)
                else:
                    errors.append(None)
        return errors

    def existing_robots(self, robot_ids: set[str]) -> set[str]:
        conn = self._connection()
        with conn.transaction():
            cursor = conn.execute(f"SELECT id FROM {self.robot_table} WHERE id = ANY(%s)", [list(robot_ids)])
            return {row[0] for row in cursor.fetchall()}

    def is_integrity_error(self, exc: BaseException) -> bool:
        return isinstance(exc, psycopg.errors.ForeignKeyViolation)

    def reset(self) -> None:
        if self.conn is not None:
            self.conn.close()
        self.conn = None


class _OrmSink:
    """Write batches with bulk_create, for SQLite and other vendors."""

    def __init__(self, alias: str) -> None:
        # The writer's one thread means one Django connection, and SQLite sees a single writer.
        self.alias = alias

    def prepare(self, robot_id: str, points: Sequence[MetricPoint]) -> tuple[MetricPoint, ...]:
        # Model instances are built in the thread: they are expensive and would stall the loop.
        return tuple(points)

    def _metrics(self, entry: _Entry) -> list[Metric]:
        return [
            Metric(
                robot_id=entry.robot_id,
                skill=point.get("skill") or "",
                component=point.get("component") or "",
                name=point["name"],
                value=point["value"],
                labels=point.get("labels") or {},
                ts=datetime.fromtimestamp(point["ts"], UTC),
            )
            for point in entry.payload
        ]

    def write(self, entries: list[_Entry]) -> int:
        with transaction.atomic(using=self.alias):
            fresh = self._claim(entries)
            rows = [metric for entry in fresh for metric in self._metrics(entry)]
            Metric.objects.using(self.alias).bulk_create(rows, batch_size=1000)
        return sum(entry.rows for entry in entries) - len(rows)

    def _claim(self, entries: list[_Entry]) -> list[_Entry]:
        """Record the entries' frame ids in this transaction; return the entries not stored before."""
        frames = IngestedFrame.objects.using(self.alias)
        wanted = {(entry.robot_id, entry.frame_id) for entry in entries if entry.frame_id is not None}
        if not wanted:
            return entries
        known = set(
            frames.filter(
                robot_id__in={robot for robot, _ in wanted}, frame_id__in={frame for _, frame in wanted}
            ).values_list("robot_id", "frame_id")
        )
        fresh = []
        for entry in entries:
            key = (entry.robot_id, entry.frame_id)
            if entry.frame_id is None:
                fresh.append(entry)
            elif key not in known:
                known.add(key)
                fresh.append(entry)
        frames.bulk_create(
            [IngestedFrame(robot_id=e.robot_id, frame_id=e.frame_id) for e in fresh if e.frame_id is not None]
        )
        return fresh

    def write_each(self, entries: list[_Entry]) -> list[BaseException | None]:
        errors: list[BaseException | None] = []
        for entry in entries:
            try:
                self.write([entry])
            except Exception as exc:
                errors.append(exc)
            else:
                errors.append(None)
        return errors

    def existing_robots(self, robot_ids: set[str]) -> set[str]:
        robots = Metric._meta.get_field("robot").related_model._default_manager.using(self.alias)
        return set(robots.filter(pk__in=robot_ids).values_list("pk", flat=True))

    def is_integrity_error(self, exc: BaseException) -> bool:
        return isinstance(exc, IntegrityError)

    def reset(self) -> None:
        # Called in the writer's thread: Django keeps one connection per thread.
        connections[self.alias].close()


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
        self._buffer: list[_Entry] = []
        self._buffered_rows = 0
        self._buffered_since = 0.0  # monotonic time the oldest buffered frame arrived
        self._sink: _Sink | None = None
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
            self._buffer.append(_Entry(robot_id, payload, rows, future, frame_id))
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
            self._sink = _PostgresSink(self.using) if vendor == "postgresql" else _OrmSink(self.using)
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

    def _take(self) -> tuple[list[_Entry], int, float]:
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
                outcome: tuple[list[_Entry], dict[_Entry, BaseException]] | BaseException = self._write(entries)
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
        entries: list[_Entry],
        rows: int,
        since: float,
        outcome: tuple[list[_Entry], dict[_Entry, BaseException]] | BaseException,
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

    def _fail(self, entries: list[_Entry], exc: BaseException) -> None:
        for entry in entries:
            if not entry.future.done():
                entry.future.set_exception(exc)

    def _write(self, entries: list[_Entry]) -> tuple[list[_Entry], dict[_Entry, BaseException]]:
        """Write a batch and return what was written and which frames failed, retrying once (in the writer's thread)."""
        sink = self._sink
        assert sink is not None
        retried = False
        while True:
            try:
                self.rows_already_stored += sink.write(entries)
                return entries, {}
            except Exception as exc:
                if sink.is_integrity_error(exc):
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

    def _without_deleted_robots(self, entries: list[_Entry], sink: _Sink) -> list[_Entry]:
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
