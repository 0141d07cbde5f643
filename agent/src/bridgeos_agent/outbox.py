"""Keep every frame the robot owes the cloud on disk until the cloud acknowledges it.

State events and metrics are written to SQLite before they are sent and deleted only when
acked, so neither a lost connection nor an agent restart loses them; on reconnect the
backlog is sent again in order and the cloud drops duplicates by frame id.

Bound: the store holds at most ``max_bytes`` of frames. Past that, the oldest half of the
metric frames is thinned to every other frame (halving the time resolution of old metrics,
again and again if needed) and, when only state events are left, nothing more is dropped:
state events are never discarded, whatever their volume.

The same file remembers the ids of the cloud's frames this robot applied (and the answer it
gave), the newest ``APPLIED_KEPT``, so a command the cloud resends after the agent was killed
and restarted is answered again, not applied twice.
"""

from __future__ import annotations

import sqlite3
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Envelope, Event

__all__ = ["AppliedFrames", "Outbox", "OutboxStats"]

DEFAULT_MAX_BYTES = 64 * 1024 * 1024
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


class Outbox:
    """A durable FIFO of unacknowledged frames in one SQLite file."""

    def __init__(self, path: Path | str, *, max_bytes: int = DEFAULT_MAX_BYTES) -> None:
        if max_bytes < 1024:
            raise ValueError("max_bytes must be at least 1024")
        self.path = Path(path)
        self.max_bytes = max_bytes
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
        self.applied = AppliedFrames(self._db)

    def put(self, envelope: Envelope) -> str:
        """Store a frame before it is sent; return its encoded text. A stored id is kept as is."""
        text = protocol.encode(envelope)
        cursor = self._db.execute(
            "INSERT OR IGNORE INTO outbox (id, metrics, frame) VALUES (?, ?, ?)",
            (envelope.id, envelope.event == Event.METRICS, text),
        )
        if cursor.rowcount:
            self._bytes += len(text)
            if self._bytes > self.max_bytes:
                self._thin()
        return text

    def ack(self, frame_id: str) -> bool:
        """Forget an acknowledged frame; return whether it was held."""
        row = self._db.execute("DELETE FROM outbox WHERE id = ? RETURNING length(frame)", (frame_id,)).fetchone()
        if row is None:
            return False
        self._bytes -= row[0]
        return True

    def backlog(self, *, after: int = 0, batch: int = 500) -> Iterator[tuple[int, str, str]]:
        """Yield (seq, id, frame text) of every held frame in the order it was stored."""
        while True:
            rows = self._db.execute(
                "SELECT seq, id, frame FROM outbox WHERE seq > ? ORDER BY seq LIMIT ?", (after, batch)
            ).fetchall()
            yield from rows
            if len(rows) < batch:
                return
            after = rows[-1][0]

    def frame(self, frame_id: str) -> str | None:
        """Return the text of a held frame, or None once it was acked."""
        row = self._db.execute("SELECT frame FROM outbox WHERE id = ?", (frame_id,)).fetchone()
        return row[0] if row else None

    def __contains__(self, frame_id: object) -> bool:
        return self._db.execute("SELECT 1 FROM outbox WHERE id = ?", (frame_id,)).fetchone() is not None

    def __len__(self) -> int:
        return self._db.execute("SELECT count(*) FROM outbox").fetchone()[0]

    def stats(self) -> OutboxStats:
        """Return the outbox's size."""
        frames, metric_frames = self._db.execute("SELECT count(*), coalesce(sum(metrics), 0) FROM outbox").fetchone()
        return OutboxStats(frames, metric_frames, self._bytes, self.thinned_frames)

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
