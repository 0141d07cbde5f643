"""Storing, querying and pruning component logs."""

from __future__ import annotations

import base64
import binascii
import json
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

import psycopg
from django.conf import settings
from django.db import DataError, connection, transaction
from django.db.models import Q, QuerySet, Sum
from django.utils import timezone

from bridgeos_agent.protocol import LogLine
from monitoring.services import storable

from . import partitions
from .choices import LEVEL_NAME, LEVEL_RANK, UNLEVELLED_RANK
from .live import publish_lines_on_commit
from .models import ComponentLog, DroppedLines

TABLE = ComponentLog._meta.db_table
_INSERT_SQL = (
    f"INSERT INTO {TABLE} (robot_id, skill, component, location, seq, ts, stream, level, text) "
    "SELECT %s, %s, %s, %s, u.seq, to_timestamp(u.ts), u.stream, u.level, u.text "
    "FROM unnest(%s::bigint[], %s::float8[], %s::text[], %s::smallint[], %s::text[])"
    " AS u(seq, ts, stream, level, text) "
    "ON CONFLICT DO NOTHING RETURNING seq"
)
# A query of the log (a regular expression most of all) must not hold a database connection for long.
QUERY_TIMEOUT_MS = 15_000


class BadQuery(ValueError):
    """A query the database refused (a regular expression it cannot compile): the caller's `q` is wrong."""


def _line(line: LogLine | dict[str, Any]) -> LogLine:
    return line if isinstance(line, LogLine) else LogLine.model_validate(line)


def store_lines(
    robot_id: str,
    skill: str,
    component: str,
    location: str,
    lines: Sequence[LogLine | dict[str, Any]],
    dropped: int = 0,
) -> int:
    """Store a component's lines once each (by their key), push the new ones to live tails; return how many were new."""
    parsed = [_line(line) for line in lines]
    with transaction.atomic():
        if connection.vendor == "postgresql":
            new_seqs = _insert_postgres(robot_id, skill, component, location, parsed)
        else:
            new_seqs = _insert_orm(robot_id, skill, component, location, parsed)
        fresh = [line for line in parsed if line.seq in new_seqs]
        # A resent frame stores nothing again and so counts its drops once (a frame of drops alone may count twice).
        if dropped and (fresh or not parsed):
            DroppedLines.objects.create(
                robot_id=robot_id, skill=skill, component=component, location=location, ts=timezone.now(), count=dropped
            )
        if fresh or dropped:
            publish_lines_on_commit(robot_id, skill, component, location, fresh, dropped)
    return len(fresh)


def _insert_postgres(robot_id: str, skill: str, component: str, location: str, lines: list[LogLine]) -> set[int]:
    if not lines:
        return set()
    connection.ensure_connection()
    # Server-side binding (Django's cursors bind on the client): five arrays of thousands of values are
    # sent as parameters, not quoted into the statement's text, which doubles the rate of a flood of lines.
    with psycopg.Cursor(connection.connection) as cursor:
        cursor.execute(
            _INSERT_SQL,
            [
                robot_id,
                skill,
                component,
                location,
                [line.seq for line in lines],
                [line.ts for line in lines],
                [line.stream for line in lines],
                [None if line.level is None else LEVEL_RANK[line.level] for line in lines],
                # PostgreSQL refuses NUL in text: one such line must be kept, not fail its frame.
                [storable(line.text) for line in lines],
            ],
        )
        return {row[0] for row in cursor.fetchall()}


def _insert_orm(robot_id: str, skill: str, component: str, location: str, lines: list[LogLine]) -> set[int]:
    """Insert the lines not stored yet (SQLite, make run's default: one writer at a time)."""
    if not lines:
        return set()
    keys = {(line.seq, _when(line.ts)) for line in lines}
    known = set(
        ComponentLog.objects.filter(
            robot_id=robot_id,
            skill=skill,
            component=component,
            location=location,
            seq__in={seq for seq, _ in keys},
        ).values_list("seq", "ts")
    )
    rows = []
    for line in lines:
        key = (line.seq, _when(line.ts))
        if key in known:
            continue
        known.add(key)
        rows.append(
            ComponentLog(
                robot_id=robot_id,
                skill=skill,
                component=component,
                location=location,
                seq=line.seq,
                ts=key[1],
                stream=line.stream,
                level=None if line.level is None else LEVEL_RANK[line.level],
                text=line.text,
            )
        )
    ComponentLog.objects.bulk_create(rows, batch_size=500)
    return {row.seq for row in rows}


def _when(ts: float) -> datetime:
    return datetime.fromtimestamp(ts, UTC)


def line_dict(row: ComponentLog) -> dict[str, Any]:
    """Return a stored line as a LogLine dict (seq, ts as unix seconds, stream, level, text)."""
    return {
        "seq": row.seq,
        "ts": row.ts.timestamp(),
        "stream": row.stream,
        "level": row.level_name,
        "text": row.text,
    }


# --------------------------------------------------------------------------- reading


@dataclass(frozen=True)
class LogFilters:
    """What a query of one robot's log asks for (validated by the API)."""

    skill: str | None = None
    component: str | None = None
    location: str | None = None
    since: datetime | None = None
    until: datetime | None = None
    level: str | None = None
    q: str | None = None
    regex: bool = False


def _escape_like(text: str) -> str:
    return text.replace("\\", "\\\\").replace("%", "\\%").replace("_", "\\_")


def lines_matching(robot_id: str, filters: LogFilters) -> QuerySet[ComponentLog]:
    """Return the robot's lines matching the filters, unordered."""
    lines = ComponentLog.objects.filter(robot_id=robot_id)
    for field in ("skill", "component", "location"):
        value = getattr(filters, field)
        if value is not None:
            lines = lines.filter(**{field: value})
    if filters.since is not None:
        lines = lines.filter(ts__gte=filters.since)
    if filters.until is not None:
        lines = lines.filter(ts__lt=filters.until)
    rank = LEVEL_RANK[filters.level] if filters.level is not None else 0
    if 0 < rank <= UNLEVELLED_RANK:
        # A line that says no level counts as info.
        lines = lines.filter(Q(level__gte=rank) | Q(level__isnull=True))
    elif rank > UNLEVELLED_RANK:
        lines = lines.filter(level__gte=rank)
    if filters.q:
        if filters.regex:
            lines = lines.filter(text__iregex=filters.q)
        else:
            lines = lines.filter(text__ilike=f"%{_escape_like(filters.q)}%")
    return lines


def encode_cursor(row: ComponentLog) -> str:
    """Return the opaque cursor of the page after this line."""
    micros = round(row.ts.timestamp() * 1_000_000)
    return base64.urlsafe_b64encode(json.dumps([micros, row.id]).encode()).decode().rstrip("=")


def decode_cursor(cursor: str) -> tuple[datetime, int]:
    """Return the (ts, id) a cursor stands for; ValueError if it is not one of ours."""
    try:
        micros, row_id = json.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
        if not isinstance(micros, int) or not isinstance(row_id, int):
            raise ValueError("not a cursor")
        return datetime.fromtimestamp(micros / 1_000_000, UTC), row_id
    except (binascii.Error, json.JSONDecodeError, TypeError, ValueError, OverflowError, UnicodeDecodeError):
        raise ValueError("not a cursor of this API") from None


def page_of_lines(
    robot_id: str,
    filters: LogFilters,
    *,
    order: str = "desc",
    limit: int = 200,
    cursor: tuple[datetime, int] | None = None,
) -> tuple[list[ComponentLog], str | None]:
    """Return one page of matching lines in order, and the cursor of the next page (None at the end)."""
    lines = lines_matching(robot_id, filters)
    if cursor is not None:
        ts, row_id = cursor
        if order == "desc":
            lines = lines.filter(Q(ts__lt=ts) | Q(ts=ts, id__lt=row_id))
        else:
            lines = lines.filter(Q(ts__gt=ts) | Q(ts=ts, id__gt=row_id))
    lines = lines.order_by("-ts", "-id") if order == "desc" else lines.order_by("ts", "id")
    rows = _run(lambda: list(lines[: limit + 1]))
    more = len(rows) > limit
    rows = rows[:limit]
    return rows, encode_cursor(rows[-1]) if more and rows else None


def iter_lines(robot_id: str, filters: LogFilters, *, batch: int = 5000) -> Iterator[ComponentLog]:
    """Yield every matching line, oldest first, a page at a time."""
    cursor = None
    while True:
        rows, _ = page_of_lines(robot_id, filters, order="asc", limit=batch, cursor=cursor)
        yield from rows
        if len(rows) < batch:
            return
        cursor = (rows[-1].ts, rows[-1].id)


def _run(query: Any) -> Any:
    """Run a query under a time limit; a regular expression the database refuses is the caller's BadQuery."""
    try:
        with transaction.atomic():
            if connection.vendor == "postgresql":
                with connection.cursor() as cursor:
                    cursor.execute(f"SET LOCAL statement_timeout = {QUERY_TIMEOUT_MS}")
            return query()
    except DataError as exc:
        raise BadQuery(str(exc).splitlines()[0]) from None


def dropped_count(robot_id: str, filters: LogFilters) -> int:
    """Return how many lines of the matching components their robot counted as not shipped, in the time range."""
    drops = DroppedLines.objects.filter(robot_id=robot_id)
    for field in ("skill", "component", "location"):
        value = getattr(filters, field)
        if value is not None:
            drops = drops.filter(**{field: value})
    if filters.since is not None:
        drops = drops.filter(ts__gte=filters.since)
    if filters.until is not None:
        drops = drops.filter(ts__lt=filters.until)
    return drops.aggregate(total=Sum("count"))["total"] or 0


def format_line(row: ComponentLog) -> str:
    """Format a line for a download: `2026-12-04T19:00:00.123Z robot stdout INFO skill/component: text`."""
    ts = row.ts.astimezone(UTC)
    stamp = ts.strftime("%Y-%m-%dT%H:%M:%S.") + f"{ts.microsecond // 1000:03d}Z"
    level = (LEVEL_NAME.get(row.level) or "-").upper() if row.level is not None else "-"
    return f"{stamp} {row.location} {row.stream} {level} {row.skill}/{row.component}: {row.text}\n"


def tail_lines(robot_id: str, skill: str, component: str, location: str, tail: int) -> list[ComponentLog]:
    """Return a component's last ``tail`` stored lines, oldest first."""
    if tail <= 0:
        return []
    rows = ComponentLog.objects.filter(robot_id=robot_id, skill=skill, component=component, location=location)
    return list(reversed(rows.order_by("-seq")[:tail]))


def newest_seq(robot_id: str, skill: str, component: str, location: str) -> int:
    """Return the highest stored seq of a component's log (0 when none)."""
    rows = ComponentLog.objects.filter(robot_id=robot_id, skill=skill, component=component, location=location)
    return rows.order_by("-seq").values_list("seq", flat=True).first() or 0


def known_components(robot_id: str, skill: str | None, component: str | None) -> list[tuple[str, str]]:
    """Return the robot's (skill, component) pairs matching a tail's subscription, as its Skills declare them."""
    from skills.models import Component

    components = Component.objects.filter(skill__robot_id=robot_id)
    if skill is not None:
        components = components.filter(skill__skill_id=skill)
    if component is not None:
        components = components.filter(component_id=component)
    return sorted(components.values_list("skill__skill_id", "component_id"))


# --------------------------------------------------------------------------- retention


def prune_logs(older_than: timedelta | None = None, *, now: datetime | None = None, batch: int = 50_000) -> int:
    """Remove lines older than the retention age (whole day partitions on PostgreSQL); return how many went."""
    if older_than is None:
        older_than = timedelta(days=settings.BRIDGEOS["LOG_RETENTION_DAYS"])
    now = now or timezone.now()
    cutoff = now - older_than
    deleted = 0
    if partitions.is_partitioned():
        deleted += partitions.drop_expired_partitions(cutoff)
        partitions.ensure_partitions(now)
    DroppedLines.objects.filter(ts__lt=cutoff).delete()
    # The day the cutoff falls in (and the default partition, SQLite's whole table) go row by row, in bounded batches.
    while True:
        with transaction.atomic():
            ids = list(ComponentLog.objects.filter(ts__lt=cutoff).values_list("id", flat=True)[:batch])
            if not ids:
                return deleted
            if connection.vendor == "postgresql":
                with connection.cursor() as cursor:
                    cursor.execute(f"DELETE FROM {TABLE} WHERE ts < %s AND id = ANY(%s)", [cutoff, ids])
            else:
                ComponentLog.objects.filter(id__in=ids).delete()
        deleted += len(ids)


def forget_robot(robot_id: str) -> None:
    """Delete every line and drop count of a robot (it was deleted: its id may be given to another)."""
    with transaction.atomic():
        ComponentLog.objects.filter(robot_id=robot_id)._raw_delete(ComponentLog.objects.db)
        DroppedLines.objects.filter(robot_id=robot_id).delete()


def valid_regex(pattern: str) -> str | None:
    """Return why a regular expression is refused, or None if Python compiles it (the database may still refuse)."""
    try:
        re.compile(pattern)
    except re.error as exc:
        return f"Not a valid regular expression: {exc}."
    return None
