"""Keep every frame the robot owes the cloud on disk until the cloud acknowledges it.

State events and metrics are written to SQLite before they are sent and deleted only when
acked, so neither a lost connection nor an agent restart loses them; on reconnect the
backlog is sent again in order and the cloud drops duplicates by frame id.

Bound: the store holds at most ``max_bytes`` of frames. Past that, the oldest half of the
metric frames is thinned to every other frame (halving the time resolution of old metrics,
again and again if needed) and, when only state events are left, nothing more is dropped:
state events are never discarded, whatever their volume.

Full disk: a frame SQLite cannot write ("database or disk is full") is not lost. It is kept
in memory instead, in its place in the order, until it is acked (sent again on reconnect like
the stored ones): state events always, metric frames up to ``memory_bytes`` of memory. Past
that budget the oldest metric frames in memory go first (never a state event): their points
are counted in ``unstored_points`` and handed to the session (``evictions``), which counts them
dropped unless they are in flight on the live link; a metric frame that does not fit at all is
not kept (the session sends it once when connected, and counts it dropped when not). The agent
says once that the disk is full, once that the budget is spent, and once that it has room again.

The same file remembers the ids of the cloud's frames this robot applied (and the answer it
gave), the newest ``APPLIED_KEPT``, so a command the cloud resends after the agent was killed
and restarted is answered again, not applied twice.
"""

from __future__ import annotations

import heapq
import logging
import sqlite3
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Envelope, Event

__all__ = ["DEFAULT_MEMORY_BYTES", "AppliedFrames", "Outbox", "OutboxStats", "disk_full"]

logger = logging.getLogger("bridgeos_agent")

DEFAULT_MAX_BYTES = 64 * 1024 * 1024
# Metric frames kept in memory on a full disk: hours of a robot's metrics at 10 points/s.
DEFAULT_MEMORY_BYTES = 8 * 1024 * 1024
# As many applied ids as the session's in-memory dedup window; trimmed every APPLIED_TRIM_EVERY adds.
APPLIED_KEPT = 2000
APPLIED_TRIM_EVERY = 200

SCHEMA = """
CREATE TABLE IF NOT EXISTS outbox (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    metrics INTEGER NOT NULL,
    frame TEXT NOT NULL
);
CREATE INDEX IF NOT EXISTS outbox_metrics ON outbox (metrics, seq);
CREATE TABLE IF NOT EXISTS applied (
    seq INTEGER PRIMARY KEY AUTOINCREMENT,
    id TEXT NOT NULL UNIQUE,
    answer TEXT NOT NULL
);
"""


@dataclass(frozen=True, slots=True)
class OutboxStats:
    """Describe what the outbox holds and what it had to thin."""

    frames: int
    metric_frames: int
    bytes: int
    thinned_frames: int
    # Frames kept in memory (written while the disk was full) and metric points not kept.
    spilled_frames: int = 0
    unstored_points: int = 0
    spilled_bytes: int = 0
    spilled_points: int = 0  # metric points ever kept in memory for want of disk


def disk_full(exc: sqlite3.Error) -> bool:
    """Tell whether SQLite failed for want of disk space (SQLITE_FULL, or an I/O error on write)."""
    code = getattr(exc, "sqlite_errorcode", None)
    if code is not None:
        return code & 0xFF in (sqlite3.SQLITE_FULL, sqlite3.SQLITE_IOERR)
    return "full" in str(exc)


class Outbox:
    """A durable FIFO of unacknowledged frames in one SQLite file."""

    def __init__(
        self, path: Path | str, *, max_bytes: int = DEFAULT_MAX_BYTES, memory_bytes: int = DEFAULT_MEMORY_BYTES
    ) -> None:
        if max_bytes < 1024:
            raise ValueError("max_bytes must be at least 1024")
        if memory_bytes < 0:
            raise ValueError("memory_bytes must not be negative")
        self.path = Path(path)
        self.max_bytes = max_bytes
        self.memory_bytes = memory_bytes
        self.path.parent.mkdir(parents=True, exist_ok=True)
        # One connection used from the event loop's thread only; autocommit per statement.
        self._db = sqlite3.connect(self.path, isolation_level=None, check_same_thread=False)
        # WAL with synchronous=NORMAL survives a crash of the agent (not of the OS) at
        # ~20 µs per insert; FULL would fsync every frame.
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=NORMAL")
        self._db.executescript(SCHEMA)
        self._bytes = self._db.execute("SELECT coalesce(sum(length(frame)), 0) FROM outbox").fetchone()[0]
        self.thinned_frames = 0
        self.unstored_points = 0
        self.spilled_points = 0
        self.disk_full = False
        # id -> ((seq of the last stored frame, n), text): frames the full disk could not take.
        self._spilled: dict[str, tuple[tuple[int, int], str]] = {}
        self._spilled_metrics: dict[str, int] = {}  # id -> points of the metric frames among them, oldest first
        self._spilled_bytes = 0
        self._over_budget = False
        self._evicted: list[tuple[str, str, int]] = []  # (id, text, points) dropped from memory, not yet told
        self._spill_count = 0
        self._reclaimed_at = -1e9
        self._acked: set[str] = set()  # acked while the disk was full: still on disk, no longer owed
        self.applied = AppliedFrames(self._db)

    def put(self, envelope: Envelope) -> str:
        """Store a frame before it is sent; return its encoded text. A stored id is kept as is."""
        text = protocol.encode(envelope)
        metrics = envelope.event == Event.METRICS
        try:
            cursor = self._db.execute(
                "INSERT OR IGNORE INTO outbox (id, metrics, frame) VALUES (?, ?, ?)", (envelope.id, metrics, text)
            )
        except sqlite3.Error as exc:
            if not disk_full(exc):
                raise
            self._full(exc)
            if self._reclaim():
                return self.put(envelope)
            points = len(envelope.data.get("metrics", ())) if metrics else None
            self.keep(envelope.id, text, points=points)
            if points is not None and envelope.id in self._spilled:
                self.spilled_points += points
            return text
        if self.disk_full:
            self._room_again()
        if self._acked:
            self._forget_acked()
        if cursor.rowcount:
            self._bytes += len(text)
            if self._bytes > self.max_bytes:
                try:
                    self._thin()
                except sqlite3.Error as exc:
                    if not disk_full(exc):
                        raise
                    self._full(exc)
        return text

    def keep(self, frame_id: str, text: str, *, points: int | None = None) -> None:
        """Hold in memory, until acked, a frame the full disk could not take (sent again on reconnect).

        ``points`` marks a metric frame (with that many points): within ``memory_bytes`` only.
        """
        if frame_id in self._spilled:
            return
        self._spill_count += 1
        self._spilled[frame_id] = ((self._last_seq(), self._spill_count), text)
        self._spilled_bytes += len(text)
        if points is not None:
            self._spilled_metrics[frame_id] = points
        self._fit(frame_id)

    def _fit(self, newest: str) -> None:
        """Drop the oldest metric frames kept in memory until under the budget (state events stay)."""
        while self._spilled_bytes > self.memory_bytes and self._spilled_metrics:
            frame_id = next(iter(self._spilled_metrics))
            points = self._spilled_metrics.pop(frame_id)
            _, text = self._spilled.pop(frame_id)
            self._spilled_bytes -= len(text)
            self.unstored_points += points
            if frame_id != newest:
                self._evicted.append((frame_id, text, points))  # the newest is simply not held: its sender sees
            if not self._over_budget:
                self._over_budget = True
                logger.warning(
                    "the outbox %s keeps %.3g MiB in memory while the disk is full: the oldest metric frames "
                    "in memory are dropped from now on (their points counted unstored; state events are kept)",
                    self.path,
                    self.memory_bytes / (1024 * 1024),
                )

    def evictions(self) -> list[tuple[str, str, int]]:
        """Return (id, text, points) of the metric frames dropped from memory since the last call."""
        evicted, self._evicted = self._evicted, []
        return evicted

    def held(self, frame_id: str) -> bool:
        """Tell whether a frame is kept until acked (on disk or, on a full disk, in memory)."""
        return frame_id in self

    def ack(self, frame_id: str) -> bool:
        """Forget an acknowledged frame; return whether it was held."""
        spilled = self._spilled.pop(frame_id, None)
        if spilled is not None:
            self._spilled_bytes -= len(spilled[1])
            self._spilled_metrics.pop(frame_id, None)
            return True
        if frame_id in self._acked:
            return True
        try:
            row = self._delete(frame_id)
        except sqlite3.Error as exc:
            if not disk_full(exc):
                raise
            self._full(exc)
            if not (self._reclaim() and self._forget_acked()):
                # Forgotten on disk once it has room (a restart meanwhile resends it: the cloud drops it by id).
                if frame_id in self:
                    self._acked.add(frame_id)
                    return True
                return False
            row = self._delete(frame_id)
        if row is None:
            return False
        self._bytes -= row[0]
        return True

    def _delete(self, frame_id: str) -> tuple[int] | None:
        return self._db.execute("DELETE FROM outbox WHERE id = ? RETURNING length(frame)", (frame_id,)).fetchone()

    def _forget_acked(self) -> bool:
        """Delete the frames acked while the disk was full; say whether it could."""
        try:
            for frame_id in list(self._acked):
                row = self._delete(frame_id)
                if row is not None:
                    self._bytes -= row[0]
                self._acked.discard(frame_id)
        except sqlite3.Error as exc:
            if not disk_full(exc):
                raise
            return False
        return True

    def backlog(self, *, after: int = 0, batch: int = 500) -> Iterator[tuple[int, str, str]]:
        """Yield (seq, id, frame text) of every held frame in the order it was stored."""
        spilled = sorted((key, frame_id, text) for frame_id, (key, text) in self._spilled.items())
        if spilled:
            # Kept-in-memory frames go in after the frame stored just before them.
            stored = (((seq, 0), frame_id, text) for seq, frame_id, text in self._stored_backlog(after, batch))
            for (seq, n), frame_id, text in heapq.merge(stored, spilled):
                if n and frame_id not in self._spilled:
                    continue  # acked or dropped from memory since the backlog began
                yield seq, frame_id, text
            return
        yield from self._stored_backlog(after, batch)

    def _stored_backlog(self, after: int, batch: int) -> Iterator[tuple[int, str, str]]:
        while True:
            rows = self._db.execute(
                "SELECT seq, id, frame FROM outbox WHERE seq > ? ORDER BY seq LIMIT ?", (after, batch)
            ).fetchall()
            yield from (row for row in rows if row[1] not in self._acked)
            if len(rows) < batch:
                return
            after = rows[-1][0]

    def frame(self, frame_id: str) -> str | None:
        """Return the text of a held frame, or None once it was acked."""
        spilled = self._spilled.get(frame_id)
        if spilled is not None:
            return spilled[1]
        if frame_id in self._acked:
            return None
        row = self._db.execute("SELECT frame FROM outbox WHERE id = ?", (frame_id,)).fetchone()
        return row[0] if row else None

    def __contains__(self, frame_id: object) -> bool:
        if frame_id in self._spilled:
            return True
        if frame_id in self._acked:
            return False
        return self._db.execute("SELECT 1 FROM outbox WHERE id = ?", (frame_id,)).fetchone() is not None

    def __len__(self) -> int:
        return self._db.execute("SELECT count(*) FROM outbox").fetchone()[0] + len(self._spilled) - len(self._acked)

    def stats(self) -> OutboxStats:
        """Return the outbox's size."""
        frames, metric_frames = self._db.execute("SELECT count(*), coalesce(sum(metrics), 0) FROM outbox").fetchone()
        spilled = len(self._spilled)
        return OutboxStats(
            frames + spilled - len(self._acked),
            metric_frames,
            self._bytes,
            self.thinned_frames,
            spilled,
            self.unstored_points,
            self._spilled_bytes,
            self.spilled_points,
        )

    def _last_seq(self) -> int:
        row = self._db.execute("SELECT coalesce(max(seq), 0) FROM outbox").fetchone()
        return int(row[0])

    def _reclaim(self, clock: Callable[[], float] = time.monotonic) -> bool:
        """Give the write-ahead log's space back to the disk (at most once a second); say whether it worked.

        The log is only checkpointed after a commit that succeeds, so on a full disk it would
        keep every byte it holds and the outbox would stay full after the disk has room again.
        """
        now = clock()
        if now - self._reclaimed_at < 1.0:
            return False
        self._reclaimed_at = now
        try:
            busy, _, _ = self._db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()
        except sqlite3.Error:
            return False
        return busy == 0

    def _full(self, exc: sqlite3.Error) -> None:
        if not self.disk_full:
            self.disk_full = True
            logger.warning(
                "disk full under the outbox %s (%s): the agent runs on; frames are kept in memory until acked "
                "(metric frames up to %.3g MiB, past that the oldest are dropped and their points counted "
                "unstored, and dropped when not sent; state events always)",
                self.path,
                exc,
                self.memory_bytes / (1024 * 1024),
            )

    def _room_again(self) -> None:
        self.disk_full = False
        self._over_budget = False
        logger.warning(
            "the outbox %s can write again: %d metric point(s) kept in memory, %d could not be kept, "
            "while the disk was full",
            self.path,
            self.spilled_points,
            self.unstored_points,
        )

    def oldest_ts(self) -> float | None:
        """Return when the oldest held frame was made (its envelope's ts), or None when empty."""
        row = self._db.execute("SELECT json_extract(frame, '$.ts') FROM outbox ORDER BY seq LIMIT 1").fetchone()
        return None if row is None or row[0] is None else float(row[0])

    def close(self) -> None:
        """Close the database file."""
        self._db.close()

    def _thin(self) -> None:
        """Drop every other frame of the oldest half of metric frames until under the bound."""
        while self._bytes > self.max_bytes:
            seqs = [row[0] for row in self._db.execute("SELECT seq FROM outbox WHERE metrics ORDER BY seq")]
            if len(seqs) < 2:
                return  # only state events (and at most one metric frame) left: keep them all
            victims = seqs[: max(2, len(seqs) // 2)][::2]
            freed = 0
            for chunk in range(0, len(victims), 500):
                part = victims[chunk : chunk + 500]
                marks = ",".join("?" * len(part))
                freed += self._db.execute(
                    f"SELECT coalesce(sum(length(frame)), 0) FROM outbox WHERE seq IN ({marks})", part
                ).fetchone()[0]
                self._db.execute(f"DELETE FROM outbox WHERE seq IN ({marks})", part)
            self._bytes -= freed
            self.thinned_frames += len(victims)


class AppliedFrames:
    """The ids of the cloud's frames this robot applied, with the answer it gave, kept on disk."""

    def __init__(self, db: sqlite3.Connection, *, kept: int = APPLIED_KEPT) -> None:
        self._db = db
        self.kept = kept
        self._added = 0

    def add(self, frame_id: str, answer: str) -> None:
        """Remember that a frame was applied and how it was answered (no fsync: WAL, synchronous=NORMAL)."""
        self._db.execute("INSERT OR REPLACE INTO applied (id, answer) VALUES (?, ?)", (frame_id, answer))
        self._added += 1
        if self._added >= APPLIED_TRIM_EVERY:
            self._added = 0
            self._trim()

    def load(self) -> list[tuple[str, str]]:
        """Return (id, answer) of the newest ``kept`` applied frames, oldest first."""
        rows = self._db.execute("SELECT id, answer FROM applied ORDER BY seq DESC LIMIT ?", (self.kept,)).fetchall()
        return rows[::-1]

    def __len__(self) -> int:
        return self._db.execute("SELECT count(*) FROM applied").fetchone()[0]

    def _trim(self) -> None:
        """Forget all but the newest ``kept`` ids."""
        self._db.execute(
            "DELETE FROM applied WHERE seq <= (SELECT coalesce(max(seq), 0) FROM applied) - ?", (self.kept,)
        )
