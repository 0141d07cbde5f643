"""Read what components print: split it into lines, cut the long ones, and tell each line's level.

A process component writes its stdout and stderr to files (``FileTail`` follows them from a
saved position: the component outlives an agent restart, which a pipe the agent holds would
not let it); a container's output comes from Docker's log stream with Docker's own timestamps
(``DockerFollower``, one thread per container). Both give ``Entry`` tuples: (unix time,
stream, level, text). Nothing here touches the event loop: the capture runs in a thread.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import os
import re
import struct
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping
from datetime import datetime
from pathlib import Path
from typing import Any, Protocol

from bridgeos_agent.protocol import MAX_LOG_LINE_CHARS

__all__ = [
    "CUT_MARK",
    "DockerFollower",
    "DockerFollowers",
    "Entry",
    "FileTail",
    "LogSource",
    "cut",
    "parse_level",
    "split_lines",
]

Entry = tuple[float, str, str | None, str]  # (unix time, "stdout"|"stderr", level or None, text)

CUT_MARK = "…[cut]"
# A line longer than this many bytes is cut there, even before its end has been written.
MAX_LINE_BYTES = 4 * MAX_LOG_LINE_CHARS
READ_CHUNK = 1024 * 1024  # bytes read from a file at once: big reads, few syscalls, short GIL holds
PAGE = 4096
RESTART_AT = (
    1 << 30
)  # a file's offsets past this: emptied (when quiet) rather than punched on, to stay far from its size limit
_LIBC = ctypes.CDLL(None, use_errno=True)
_KEEP_SIZE, _PUNCH_HOLE = 0x01, 0x02  # fallocate(2) modes
READ_CHUNKS = 4  # at most per file and pass: a backlog left while the agent was down is taken in parts
# Reads to the end and tries at emptying a file over its size, per pass: the window between the
# last read and the truncation is then a few microseconds, so a line written just then is rare.
EMPTY_TRIES = 8

_WORDS = {
    "trace": "debug",
    "debug": "debug",
    "info": "info",
    "notice": "info",
    "warn": "warning",
    "warning": "warning",
    "err": "error",
    "error": "error",
    "crit": "critical",
    "critical": "critical",
    "fatal": "critical",
    "alert": "critical",
    "emerg": "critical",
    "panic": "critical",
}
_UPPER = "DEBUG|INFO|WARN|WARNING|ERROR|FATAL|CRITICAL"
# ROS 1 and 2 consoles: "[INFO] [1700000000.1]: ...", "[ WARN] ...", colour codes first, and a
# ros2 launch prefix ("[talker-1] [INFO] ...").
_BRACKETED = re.compile(rf"(?:\x1b\[[0-9;]*m)*(?:\[[^\]\s]{{1,80}}\]\s*)?\[\s*({_UPPER})\s*\]")
# Python logging's default format ("WARNING:root:...") and the common "asctime - name - LEVEL - msg".
_PREFIXED = re.compile(r"(DEBUG|INFO|WARNING|ERROR|CRITICAL):")
_DASHED = re.compile(r" - (DEBUG|INFO|WARNING|ERROR|CRITICAL) - ")
_JSON_KEYS = ("level", "levelname", "severity")


def parse_level(text: str) -> str | None:
    """Return the level a line says it has (ROS, Python logging, a JSON line's level key), or None."""
    if not text:
        return None
    first = text[0]
    if first == "{":
        return _json_level(text)
    if first in "[\x1b":
        match = _BRACKETED.match(text)
        return _WORDS[match.group(1).lower()] if match else None
    match = _PREFIXED.match(text)
    if match is None and " - " in text:
        match = _DASHED.search(text, 0, 200)
    return _WORDS[match.group(1).lower()] if match else None


def _json_level(text: str) -> str | None:
    """Return the level of a JSON line from its level, levelname or severity key."""
    try:
        record = json.loads(text)
    except ValueError:
        return None
    if not isinstance(record, dict):
        return None
    for key in _JSON_KEYS:
        value = record.get(key)
        if isinstance(value, str):
            return _WORDS.get(value.strip().lower())
        if isinstance(value, int) and not isinstance(value, bool):
            # Python logging's numbers (10 debug ... 50 critical).
            return (
                "critical"
                if value >= 50
                else "error"
                if value >= 40
                else "warning"
                if value >= 30
                else ("info" if value >= 20 else "debug")
            )
    return None


def cut(text: str) -> str:
    """Cut a line longer than MAX_LOG_LINE_CHARS, saying so at its end."""
    if len(text) <= MAX_LOG_LINE_CHARS:
        return text
    return text[: MAX_LOG_LINE_CHARS - len(CUT_MARK)] + CUT_MARK


def split_lines(data: bytes, *, final: bool = False) -> tuple[list[str], int]:
    """Split bytes into cut lines; return them and how many bytes they used (a partial last line waits).

    ``final``: the writer is done, so a last line without its newline is a line too. A partial
    line longer than MAX_LINE_BYTES is taken (cut) rather than waited for.
    """
    end = data.rfind(b"\n") + 1
    rest = len(data) - end
    if final or rest > MAX_LINE_BYTES:
        end = len(data)
    if not end:
        return [], 0
    body = data[:end]
    if body.endswith(b"\n"):
        body = body[:-1]
    lines = body.decode("utf-8", errors="replace").split("\n")
    return [cut(line.removesuffix("\r")) for line in lines], end


def entries(lines: Iterable[str], when: float, stream: str) -> list[Entry]:
    """Stamp lines with a time, their stream and their level."""
    return [(when, stream, parse_level(line), line) for line in lines]


class LogSource(Protocol):
    """Where one component's output is read from, resuming at a saved position."""

    def read(self, position: Mapping[str, Any] | None, *, final: bool = False) -> tuple[list[Entry], dict[str, Any]]:
        """Return the entries after ``position`` (None: from the start) and the position after them."""
        ...


class FileTail:
    """Follow a process component's stdout and stderr files from a saved (inode, offset, freed) each.

    The ring keeps the lines, so the part of a file already read is given back to the disk once
    it passes ``max_bytes``: punched out (the file's offsets stay, nothing the component writes
    meanwhile is lost); where the file system cannot punch holes, or once the offsets pass
    ``RESTART_AT``, the file is emptied in place when read to its very end (the component appends
    at the new end; a line written in the microseconds between is lost, counted in ``emptied``).
    """

    def __init__(self, files: Mapping[str, Path], *, max_bytes: int, clock: Callable[[], float] = time.time) -> None:
        self.files = dict(files)  # stream -> path
        self.max_bytes = max_bytes
        self.clock = clock
        self.emptied = 0  # how often a file was emptied with bytes written after its last read (lost)
        self.punching = True  # until the file system says it cannot
        self.skipped = 0  # lines passed over unread since the last take_skipped (dropped, oldest first)
        # Unread output past this many bytes is passed over, counted, down to its newest keep_bytes (the
        # log service sets its ring's size: the ring would overwrite the rest anyway). A component printing
        # faster than the passes read would otherwise fill the disk ahead of them.
        self.keep_bytes: int | None = None

    def read(self, position: Mapping[str, Any] | None, *, final: bool = False) -> tuple[list[Entry], dict[str, Any]]:
        """Return the lines written since ``position`` and the new position."""
        found: list[Entry] = []
        after: dict[str, Any] = {}
        for stream, path in self.files.items():
            saved = (position or {}).get(stream)
            lines, after[stream] = self._read_file(path, saved, final)
            found += entries(lines, self.clock(), stream)
        return found, after

    def _read_file(self, path: Path, saved: Any, final: bool) -> tuple[list[str], list[int]]:
        inode, offset, freed = (
            (int(saved[0]), int(saved[1]), int(saved[2]) if len(saved) > 2 else 0) if saved else (0, 0, 0)
        )
        try:
            fd = os.open(path, os.O_RDONLY | os.O_CLOEXEC)
        except FileNotFoundError:
            return [], [inode, offset, freed]
        lines: list[str] = []
        try:
            info = os.fstat(fd)
            if inode and info.st_ino != inode:
                # Replaced at a relaunch (the old file moved to .1): finish the old one first.
                lines += self._finish_backup(path, inode, offset)
                offset = freed = 0
            elif info.st_size < offset:
                offset = freed = 0  # emptied by someone else
            inode = info.st_ino
            if self.keep_bytes is not None and info.st_size - offset > self.keep_bytes:
                offset = self._skip(fd, offset, info.st_size - self.keep_bytes)
            for _ in range(READ_CHUNKS + EMPTY_TRIES):
                data = os.pread(fd, READ_CHUNK, offset)
                taken, used = split_lines(data, final=final and len(data) < READ_CHUNK)
                lines += taken
                offset += used
                if len(data) == READ_CHUNK and used:
                    continue  # more written than one read takes
                if offset - freed <= self.max_bytes:
                    break
                if offset < RESTART_AT and self.punching and self._punch(path, offset):
                    freed = offset - offset % PAGE
                    break
                if self._empty(path, fd, offset):
                    offset = freed = 0
                    break
                # Written to between the read and the emptying: read that too, then try again.
        finally:
            os.close(fd)
        return lines, [inode, offset, freed]

    def take_skipped(self) -> int:
        """Return how many lines were passed over unread since the last call."""
        skipped, self.skipped = self.skipped, 0
        return skipped

    def _skip(self, fd: int, offset: int, target: int) -> int:
        """Pass over whole lines from ``offset`` to the first line end at or after ``target``; return the new offset."""
        while offset < target:
            data = os.pread(fd, min(READ_CHUNK, target - offset), offset)
            if not data:
                return offset
            self.skipped += data.count(b"\n")
            offset += len(data)
        # Finish the line the target fell in, so reading resumes at a line's start.
        while data := os.pread(fd, PAGE, offset):
            end = data.find(b"\n")
            if end >= 0:
                self.skipped += 1
                return offset + end + 1
            offset += len(data)
        return offset

    def _punch(self, path: Path, offset: int) -> bool:
        """Give the disk blocks of a file's read part back, its offsets unchanged (False: cannot here)."""
        try:
            fd = os.open(path, os.O_WRONLY | os.O_CLOEXEC)
        except OSError:
            return False
        try:
            done = _LIBC.fallocate(
                fd, _PUNCH_HOLE | _KEEP_SIZE, ctypes.c_int64(0), ctypes.c_int64(offset - offset % PAGE)
            )
        finally:
            os.close(fd)
        if done != 0:
            self.punching = False  # e.g. EOPNOTSUPP: emptied in place from now on
        return done == 0

    def _finish_backup(self, path: Path, inode: int, offset: int) -> list[str]:
        backup = path.with_name(path.name + ".1")
        try:
            with backup.open("rb") as file:
                if os.fstat(file.fileno()).st_ino != inode:
                    return []
                file.seek(offset)
                return split_lines(file.read(), final=True)[0]
        except FileNotFoundError:
            return []

    def _empty(self, path: Path, fd: int, offset: int) -> bool:
        """Empty a file read to its very end (a writer outpacing the reads far over its size: anyway, counted)."""
        size = os.fstat(fd).st_size
        if size != offset and size < 16 * self.max_bytes:
            return False  # written to since the read
        if size != offset:
            self.emptied += 1
        try:
            os.truncate(path, 0)
        except OSError:
            return False
        return True


_HEADER = struct.Struct(">BxxxL")
SEEN_NS = 2_000_000_000
SEEN_MAX = 20_000
_STREAMS = {1: "stdout", 2: "stderr"}


def docker_ns(text: str) -> int:
    """Return Docker's RFC 3339 timestamp (UTC, up to nanoseconds, trailing zeros trimmed) in unix nanoseconds."""
    text = text.removesuffix("Z")
    head, _, fraction = text.partition(".")
    whole = int(datetime.fromisoformat(head + "+00:00").timestamp())
    return whole * 1_000_000_000 + int((fraction + "000000000")[:9])


def demux(buffer: bytearray) -> list[tuple[str, bytes]]:
    """Take the complete frames of Docker's multiplexed log stream out of ``buffer``."""
    frames: list[tuple[str, bytes]] = []
    start = 0
    size = len(buffer)
    while size - start >= 8:
        kind, length = _HEADER.unpack_from(buffer, start)
        if size - start - 8 < length:
            break
        frames.append((_STREAMS.get(kind, "stdout"), bytes(buffer[start + 8 : start + 8 + length])))
        start += 8 + length
    del buffer[:start]
    return frames


class DockerFollower:
    """Follow one container's log stream in a thread of its own, from a saved Docker timestamp.

    Each Docker log entry is one line, prefixed with its time; the thread keeps them until
    ``read`` takes them, at most ``max_pending`` (the oldest go first, counted in ``lost``).
    """

    def __init__(self, api: Any, container: str, *, max_pending: int = 200_000) -> None:
        self.api = api
        self.container = container
        self.max_pending = max_pending
        self.lost = 0
        self._pending: deque[tuple[int, Entry]] = deque()
        self._lock = threading.Lock()
        self._since: int | None = None  # unix nanoseconds of the newest entry taken
        self._floor: int | None = None  # taken before an agent restart: entries up to it are skipped
        # Entries taken lately, by (time, stream): Docker copies stdout and stderr apart, so a line can
        # be stamped before one it follows in the log; a stream opened again starts SEEN_NS earlier.
        self._seen: dict[tuple[int, str], None] = {}
        self._started = False
        self._closed = threading.Event()
        self.ended = threading.Event()  # the stream reached the container's end (it stopped)
        self._response: Any = None

    def read(self, position: Mapping[str, Any] | None, *, final: bool = False) -> tuple[list[Entry], dict[str, Any]]:
        """Return the lines Docker gave since the last read (from ``position`` at the first) and the new position."""
        if not self._started:
            since = (position or {}).get("since")
            self._since = self._floor = int(since) if since else None
            self._started = True
            threading.Thread(target=self._follow, name=f"bridgeos-logs-{self.container}", daemon=True).start()
        with self._lock:
            taken = list(self._pending)
            self._pending.clear()
        since = max((ns for ns, _ in taken), default=None) or (position or {}).get("since", self._since)
        return [entry for _, entry in taken], ({"since": since} if since else {})

    def close(self) -> None:
        """Stop following."""
        self._closed.set()
        response = self._response
        if response is not None:
            with contextlib.suppress(Exception):
                response.close()

    def _follow(self) -> None:
        while not self._closed.is_set():
            try:
                self._stream(follow=True)
                # The stream ends as the container stops, maybe before Docker logged its last lines.
                self._closed.wait(0.1)
                self._stream(follow=False)
            except Exception as exc:  # the daemon restarting, the container removed: tried again
                if "404" in str(exc) or type(exc).__name__ == "NotFound":
                    self.ended.set()
                    self._closed.wait(1.0)
                    continue
            self.ended.set()
            self._closed.wait(0.25)  # the container stopped: its next start is followed again

    def _stream(self, *, follow: bool) -> None:
        api = self.api
        params: dict[str, Any] = {"stdout": 1, "stderr": 1, "follow": int(follow), "timestamps": 1, "tail": "all"}
        if self._since:
            since = max(self._since - SEEN_NS, self._floor or 0)
            params["since"] = f"{since // 1_000_000_000}.{since % 1_000_000_000:09d}"
        response = api._get(api._url("/containers/{0}/logs", self.container), params=params, stream=True)
        api._raise_for_status(response)
        self._response = response
        if follow:
            self.ended.clear()
        buffer = bytearray()
        try:
            for chunk in response.raw.stream(65536, decode_content=False):
                buffer += chunk
                self._take(demux(buffer))
                if self._closed.is_set():
                    return
        finally:
            response.close()

    def _take(self, frames: list[tuple[str, bytes]]) -> None:
        fresh: list[tuple[int, Entry]] = []
        for stream, payload in frames:
            stamp, _, body = payload.partition(b" ")
            try:
                ns = docker_ns(stamp.decode("ascii"))
            except ValueError:
                ns, body = time.time_ns(), payload
            if (ns, stream) in self._seen or (self._floor is not None and ns <= self._floor):
                continue  # taken already (Docker's since is inclusive and starts earlier on purpose)
            self._seen[(ns, stream)] = None
            text = cut(body.decode("utf-8", errors="replace").removesuffix("\n").removesuffix("\r"))
            fresh.append((ns, (ns / 1e9, stream, parse_level(text), text)))
        if not fresh:
            return
        self._since = max(self._since or 0, max(ns for ns, _ in fresh))
        if len(self._seen) > SEEN_MAX:
            horizon = self._since - SEEN_NS
            self._seen = {key: None for key in self._seen if key[0] >= horizon}
        with self._lock:
            self._pending.extend(fresh)
            over = len(self._pending) - self.max_pending
            for _ in range(max(0, over)):
                self._pending.popleft()
            self.lost += max(0, over)


class DockerFollowers:
    """Keep one follower per component's current container; close those of containers gone."""

    def __init__(self) -> None:
        self._followers: dict[tuple[str, str], DockerFollower] = {}

    def follow(self, api: Any, containers: Mapping[tuple[str, str], str]) -> dict[tuple[str, str], DockerFollower]:
        """Return the followers of these containers, by (skill, component), starting new ones."""
        for key, container in containers.items():
            follower = self._followers.get(key)
            if follower is None or follower.container != container:
                if follower is not None:
                    follower.close()
                self._followers[key] = DockerFollower(api, container)
        for key in [key for key in self._followers if key not in containers]:
            self._followers.pop(key).close()
        return dict(self._followers)

    def close(self) -> None:
        """Stop following every container."""
        for follower in self._followers.values():
            follower.close()
        self._followers.clear()
