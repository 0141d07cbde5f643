"""Keep each component's last lines on disk, bounded in bytes, numbered, and marked as shipped or not.

A ring is a directory of segment files (``<first seq>.seg``, one line per log line:
``seq TAB ts TAB stream TAB level TAB text``), ``state.json`` (the last seq given, where its
source was read up to) and ``shipped`` (the seq the cloud acked up to; a file of its own, so
the loop writes it without waiting for an append in progress). Appending writes one chunk to the newest
segment; once the segments pass the ring's size the oldest is deleted, whole. So a restarted
agent finds the lines, numbers on from the last seq and ships from the cursor.
"""

from __future__ import annotations

import bisect
import contextlib
import json
import logging
import os
import threading
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridgeos_agent.logs.capture import Entry

__all__ = ["LogRing", "RingLine", "Rings"]

logger = logging.getLogger(__name__)

RingLine = tuple[int, float, str, str | None, str]  # (seq, ts, stream, level, text)

SEGMENTS = 4  # a ring holds between 3/4 and all of its size once full
MIN_SEGMENT_BYTES = 16 * 1024
_STREAM_CODE = {"stdout": "o", "stderr": "e"}
_STREAM_NAME = {"o": "stdout", "e": "stderr"}
_LEVEL_CODE = {None: "-", "debug": "d", "info": "i", "warning": "w", "error": "e", "critical": "c"}
_LEVEL_NAME = {code: name for name, code in _LEVEL_CODE.items()}


@dataclass(slots=True)
class _Segment:
    """One segment file: its first seq, size, and (seq, offset) marks to seek near any line."""

    first: int
    path: Path
    size: int = 0
    marks: list[tuple[int, int]] = field(default_factory=list)


def _encode(seq: int, entry: Entry) -> str:
    ts, stream, level, text = entry
    return f"{seq}\t{ts:.6f}\t{_STREAM_CODE.get(stream, 'o')}\t{_LEVEL_CODE.get(level, '-')}\t{text}\n"


def _decode(line: str) -> RingLine:
    seq, ts, stream, level, text = line.split("\t", 4)
    return int(seq), float(ts), _STREAM_NAME.get(stream, "stdout"), _LEVEL_NAME.get(level), text


class LogRing:
    """One component's ring: append lines, read after a seq, keep the shipped cursor; safe across threads."""

    def __init__(self, directory: Path, *, max_bytes: int) -> None:
        self.directory = directory
        self.max_bytes = max_bytes
        self._lock = threading.RLock()
        self._segments: list[_Segment] = []
        self.seq = 0  # the last seq given
        self.shipped = 0  # lines up to this seq are acked by the cloud
        self.source: dict[str, Any] = {}  # where the component's output was read up to
        directory.mkdir(parents=True, exist_ok=True)
        self._load()

    # --- loading --------------------------------------------------------------------

    def _load(self) -> None:
        state: dict[str, Any] = {}
        with contextlib.suppress(FileNotFoundError, ValueError, TypeError):
            state = dict(json.loads((self.directory / "state.json").read_text()))
        with contextlib.suppress(FileNotFoundError, ValueError):
            self.shipped = int((self.directory / "shipped").read_text())
        self.source = dict(state.get("source") or {})
        seq = int(state.get("seq") or 0)
        for path in sorted(self.directory.glob("*.seg"), key=lambda p: int(p.stem) if p.stem.isdigit() else -1):
            if not path.stem.isdigit():
                continue
            segment = _Segment(first=int(path.stem), path=path)
            last = self._scan(segment)
            if last is None:
                path.unlink(missing_ok=True)
                continue
            self._segments.append(segment)
            seq = max(seq, last)
        self.seq = seq

    def _scan(self, segment: _Segment) -> int | None:
        """Index a segment found on disk; drop a torn last line; return its last seq (None if empty)."""
        data = segment.path.read_bytes()
        end = data.rfind(b"\n") + 1
        if end < len(data):
            with open(segment.path, "r+b") as file:  # a line torn by a crash mid-write
                file.truncate(end)
        segment.size = end
        last = None
        offset = 0
        for number, raw in enumerate(data[:end].split(b"\n")[:-1]):
            seq = int(raw[: raw.index(b"\t")])
            if number % 1000 == 0:
                segment.marks.append((seq, offset))
            offset += len(raw) + 1
            last = seq
        return last

    # --- writing --------------------------------------------------------------------

    def append(self, found: Iterable[Entry], source: Mapping[str, Any] | None = None) -> int:
        """Number and keep lines (oldest first); note the source position; return the last seq."""
        with self._lock:
            chunks: list[str] = []
            seq = self.seq
            for entry in found:
                seq += 1
                chunks.append(_encode(seq, entry))
            if chunks:
                self._write(self.seq + 1, "".join(chunks).encode("utf-8", errors="replace"))
                self.seq = seq
            if source is not None:
                self.source = dict(source)
            if chunks or source is not None:
                self._save()
            return self.seq

    def skip(self, count: int) -> None:
        """Give ``count`` seqs to lines never kept (passed over unread): the shipper counts the gap dropped."""
        if count > 0:
            with self._lock:
                self.seq += count
                self._save()

    def _write(self, first: int, data: bytes) -> None:
        segment_bytes = max(MIN_SEGMENT_BYTES, self.max_bytes // SEGMENTS)
        current = self._segments[-1] if self._segments else None
        if current is None or current.size >= segment_bytes:
            current = _Segment(first=first, path=self.directory / f"{first}.seg")
            self._segments.append(current)
        with open(current.path, "ab") as file:
            file.write(data)
        current.marks.append((first, current.size))
        current.size += len(data)
        total = sum(segment.size for segment in self._segments)
        while len(self._segments) > 1 and total > self.max_bytes:
            oldest = self._segments.pop(0)
            total -= oldest.size
            oldest.path.unlink(missing_ok=True)

    def mark_shipped(self, seq: int) -> None:
        """Move the shipped cursor forward to ``seq`` (the cloud acked the lines up to it); from one thread."""
        if seq > self.shipped:
            self.shipped = min(seq, self.seq)
            self._keep("shipped", str(self.shipped))

    def _save(self) -> None:
        self._keep("state.json", json.dumps({"seq": self.seq, "source": self.source}))

    def _keep(self, name: str, text: str) -> None:
        temporary = self.directory / f"{name}.tmp"
        try:
            temporary.write_text(text)
            os.replace(temporary, self.directory / name)
        except OSError as exc:  # a full disk: the lines are still there; the state is saved next time
            logger.warning("cannot save the log ring's %s in %s: %s", name, self.directory, exc)

    # --- reading --------------------------------------------------------------------

    @property
    def first(self) -> int:
        """Return the oldest seq the ring still holds (seq + 1 when it holds none)."""
        with self._lock:
            return self._segments[0].first if self._segments else self.seq + 1

    def lines_after(self, after: int, limit: int, max_bytes: int | None = None) -> list[RingLine]:
        """Return up to ``limit`` lines with seq > ``after``, oldest first, within ``max_bytes`` of text."""
        found: list[RingLine] = []
        budget = max_bytes if max_bytes is not None else -1
        with self._lock:
            firsts = [segment.first for segment in self._segments]
            start = max(0, bisect.bisect_right(firsts, after + 1) - 1)
            for segment in self._segments[start:]:
                index = bisect.bisect_right(segment.marks, (after + 1, float("inf"))) - 1
                offset = segment.marks[index][1] if index >= 0 else 0
                try:
                    with open(segment.path, "rb") as file:
                        file.seek(offset)
                        data = file.read(segment.size - offset)
                except FileNotFoundError:
                    continue
                for raw in data.decode("utf-8", errors="replace").split("\n"):
                    if not raw:
                        continue
                    line = _decode(raw)
                    if line[0] <= after:
                        continue
                    budget -= len(line[4]) + 64
                    if len(found) >= limit or (max_bytes is not None and budget < 0 and found):
                        return found
                    found.append(line)
        return found

    def last(self, count: int) -> list[RingLine]:
        """Return the last ``count`` lines, oldest first."""
        with self._lock:
            return self.lines_after(max(0, self.seq - count), count)


class Rings:
    """Every component's ring under one directory: ``<root>/<skill>/<component>/``."""

    def __init__(self, root: Path, *, max_bytes: int) -> None:
        self.root = root
        self.max_bytes = max_bytes
        self._rings: dict[tuple[str, str], LogRing] = {}
        self._lock = threading.Lock()
        self._found = False  # the rings an earlier agent left were looked for on disk

    def get(self, skill: str, component: str, *, create: bool = True) -> LogRing | None:
        """Return a component's ring, loading it from disk (or making it) on first use."""
        key = (skill, component)
        with self._lock:
            ring = self._rings.get(key)
            if ring is None:
                directory = self.root / skill / component
                if not create and not directory.is_dir():
                    return None
                ring = self._rings[key] = LogRing(directory, max_bytes=self.max_bytes)
            return ring

    def known(self) -> list[tuple[tuple[str, str], LogRing]]:
        """Return every ring: those made since, and those an earlier agent left on disk (looked for once)."""
        if not self._found and self.root.is_dir():
            self._found = True
            for skill_dir in self.root.iterdir():
                for component_dir in skill_dir.iterdir() if skill_dir.is_dir() else ():
                    if (component_dir / "state.json").exists():
                        self.get(skill_dir.name, component_dir.name)
        with self._lock:
            return list(self._rings.items())

    def resize(self, max_bytes: int) -> None:
        """Use a new ring size (robot config ``logs.ring_bytes``) from the next append on."""
        self.max_bytes = max_bytes
        with self._lock:
            for ring in self._rings.values():
                ring.max_bytes = max_bytes
