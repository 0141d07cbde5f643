"""How batches of metric points reach the database: PostgreSQL's COPY text format, and a sink per vendor.

Every sink call but ``prepare`` runs in the metric writer's own thread (`monitoring.ingest`), one at
a time, so each sink holds one database connection.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Iterable, Sequence
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any, Protocol

import psycopg
from django.conf import settings
from django.db import connections, transaction

from .models import IngestedFrame, Metric

if TYPE_CHECKING:
    from bridgeos_agent.protocol import MetricPoint

COLUMNS = "robot_id, skill, component, name, value, labels, ts"
# Keys of Django's OPTIONS that are not libpq connection parameters.
_DJANGO_ONLY_OPTIONS = {"pool", "server_side_binding", "isolation_level", "assume_role", "cursor_factory"}
_CACHE_LIMIT = 4096


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


class Entry:
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


class Sink(Protocol):
    """Where batches go; everything but ``prepare`` runs in the writer's thread."""

    def prepare(self, robot_id: str, points: Sequence[MetricPoint]) -> Any: ...

    def write(self, entries: list[Entry]) -> int: ...

    def write_each(self, entries: list[Entry]) -> list[BaseException | None]: ...

    def existing_robots(self, robot_ids: set[str]) -> set[str]: ...

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


class RobotsDeleted(Exception):
    """A batch holds points of robots that no longer exist: the writer drops them and writes the rest."""


class PostgresSink:
    """Write batches with COPY over one psycopg connection of its own."""

    # A metric row has no foreign key to its robot: PostgreSQL checked it row by row, an index
    # lookup and a row lock each, 40 % of what storing a point cost (COPY of 100,000 rows: 0.90 s,
    # and 0.63 s more for the checks). A batch locks its robots' rows once instead, `FOR KEY SHARE`
    # as the key's check did, and a robot's deletion locks its row before deleting its points
    # (`robots.receivers`): no batch commits points of a robot after they were deleted.

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
        # In code point order, as Django's deletions lock robots (by primary key, sorted in Python):
        # a batch and a deletion of several of its robots never wait for each other's locks in a cycle.
        self.lock_sql = f'SELECT id FROM {self.robot_table} WHERE id = ANY(%s) ORDER BY id COLLATE "C" FOR KEY SHARE'
        self.conn: psycopg.Connection[Any] | None = None

    def _connection(self) -> psycopg.Connection[Any]:
        if self.conn is None or self.conn.closed:
            self.conn = psycopg.Connection.connect(self.conninfo, autocommit=False)
        return self.conn

    def prepare(self, robot_id: str, points: Sequence[MetricPoint]) -> str:
        return format_copy_rows(robot_id, points)

    def write(self, entries: list[Entry]) -> int:
        conn = self._connection()
        with conn.transaction(), conn.cursor() as cursor:
            self._lock_robots(cursor, entries)
            fresh = self._claim(cursor, entries)
            if fresh:
                with cursor.copy(self.copy_sql) as copy:
                    copy.write("".join([entry.payload for entry in fresh]))
        return sum(entry.rows for entry in entries) - sum(entry.rows for entry in fresh)

    def _lock_robots(self, cursor: psycopg.Cursor[Any], entries: list[Entry]) -> None:
        """Lock the entries' robots until this transaction ends; raise RobotsDeleted if one is gone."""
        robot_ids = {entry.robot_id for entry in entries}
        cursor.execute(self.lock_sql, [list(robot_ids)])
        if cursor.rowcount < len(robot_ids):
            raise RobotsDeleted

    def _claim(self, cursor: psycopg.Cursor[Any], entries: list[Entry]) -> list[Entry]:
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

    def write_each(self, entries: list[Entry]) -> list[BaseException | None]:
        conn = self._connection()
        errors: list[BaseException | None] = []
        with conn.transaction(), conn.cursor() as cursor:
            self._lock_robots(cursor, entries)
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

    def reset(self) -> None:
        if self.conn is not None:
            self.conn.close()
        self.conn = None


class OrmSink:
    """Write batches with bulk_create, for SQLite and other vendors."""

    def __init__(self, alias: str) -> None:
        # The writer's one thread means one Django connection, and SQLite sees a single writer.
        self.alias = alias

    def prepare(self, robot_id: str, points: Sequence[MetricPoint]) -> tuple[MetricPoint, ...]:
        # Model instances are built in the thread: they are expensive and would stall the loop.
        return tuple(points)

    def _metrics(self, entry: Entry) -> list[Metric]:
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

    def write(self, entries: list[Entry]) -> int:
        with transaction.atomic(using=self.alias):
            robot_ids = {entry.robot_id for entry in entries}
            # No foreign key to refuse them (see PostgresSink): SQLite has one writer at a time.
            if len(self.existing_robots(robot_ids)) < len(robot_ids):
                raise RobotsDeleted
            fresh = self._claim(entries)
            rows = [metric for entry in fresh for metric in self._metrics(entry)]
            Metric.objects.using(self.alias).bulk_create(rows, batch_size=1000)
        return sum(entry.rows for entry in entries) - len(rows)

    def _claim(self, entries: list[Entry]) -> list[Entry]:
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

    def write_each(self, entries: list[Entry]) -> list[BaseException | None]:
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

    def reset(self) -> None:
        # Called in the writer's thread: Django keeps one connection per thread.
        connections[self.alias].close()
