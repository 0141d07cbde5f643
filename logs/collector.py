"""Collect what the cloud copies print and store it like a robot's lines, with location "cloud".

Run by beat every BRIDGEOS_CLOUD_LOG_COLLECT_S: for each copy the cloud should run, the output
since the copy's cursor (`CloudLogCursor`) is read from its runtime, numbered on from the
cursor's seq and stored with `store_lines` in the same transaction that moves the cursor, so a
worker dying half-way stores nothing twice. The cursor row is locked while a worker reads, so
two workers never collect one copy at once.

- process: the runtime's log file (stdout and stderr go to one file there: every line is
  `stdout`), read from a byte offset; a rotation (the file copied to `.log.1` and truncated, or
  renamed) is followed by finishing the older part first. Lines get the time they were read.
- docker and swarm: Docker's log stream of the container or service, each stream on its own,
  with Docker's timestamps, from the newest timestamp collected (lines of the last second wait a
  round, so the two streams' lines are in before it moves on).
"""

from __future__ import annotations

import logging
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import docker.utils
from django.conf import settings
from django.db import transaction
from docker.api import APIClient

from bridgeos_agent.logs.capture import parse_level
from bridgeos_agent.protocol import CRASH_LOG_LINES, MAX_LOG_LINE_CHARS, MAX_LOG_LINES_PER_FRAME
from skills.cloud.runtime import object_name, runtime_name
from skills.models import CloudInstance

from .models import CloudLogCursor
from .services import line_dict, store_lines, tail_lines

log = logging.getLogger(__name__)

# One collection reads at most this much of a copy: the rest waits for the next round.
READ_BYTES = 4 * 1024 * 1024
CUT = "…[cut]"
SETTLE_NS = 1_000_000_000

# (ts, stream, text) of one line of output.
Output = tuple[float, str, str]


def _cut(text: str) -> str:
    return text if len(text) <= MAX_LOG_LINE_CHARS else text[: MAX_LOG_LINE_CHARS - len(CUT)] + CUT


# --------------------------------------------------------------------------- process runtime


def process_log_path(robot: str, skill: str, component: str) -> Path:
    """Return the file the cloud's process runtime writes a copy's output to (skills.cloud.backends' layout)."""
    return Path(settings.DATA_DIR) / "cloud" / "runtime" / "process" / robot / "logs" / skill / f"{component}.log"


def _read_from(path: Path, offset: int, limit: int) -> bytes:
    with path.open("rb") as file:
        file.seek(offset)
        return file.read(limit)


def read_process_output(path: Path, position: dict[str, Any]) -> tuple[list[Output], dict[str, Any]]:
    """Return the complete lines written to a log file since ``position``, and the position after them."""
    try:
        stat = path.stat()
    except FileNotFoundError:
        return [], position
    inode, offset = position.get("inode"), int(position.get("offset", 0))
    data = b""
    if inode is not None and (inode != stat.st_ino or stat.st_size < offset):
        # Rotated since the last read: what we had not read yet of the older part sits in .log.1.
        older = path.with_name(path.name + ".1")
        try:
            if older.stat().st_size > offset:
                data = _read_from(older, offset, READ_BYTES)
        except FileNotFoundError:
            pass
        if data and not data.endswith(b"\n"):
            data += b"\n"  # the older part ends there: its last line is complete
        offset = 0
    fresh = _read_from(path, offset, READ_BYTES)
    complete = fresh.rfind(b"\n") + 1
    if complete == 0 and len(fresh) >= READ_BYTES:
        complete = len(fresh)  # one huge line with no end in sight: take it, cut
    data += fresh[:complete]
    now = time.time()
    lines = [(now, "stdout", _cut(raw.decode("utf-8", "replace"))) for raw in data.splitlines()]
    return lines, {"inode": stat.st_ino, "offset": offset + complete}


# --------------------------------------------------------------------------- docker and swarm


def _docker_api() -> Any:
    # The engine the cloud runtimes drive (bridgeos_agent.runtime.engine.open_client): DOCKER_HOST, else its socket.
    return APIClient(**{"version": "auto", "timeout": 10, **docker.utils.kwargs_from_env()})


def parse_docker_line(raw: str) -> tuple[int, str] | None:
    """Split a line of Docker's timestamped log into (nanoseconds since the epoch, text)."""
    stamp, _, text = raw.partition(" ")
    if not stamp.endswith("Z") or "T" not in stamp:
        return None
    whole, _, fraction = stamp[:-1].partition(".")
    try:
        seconds = datetime.strptime(whole, "%Y-%m-%dT%H:%M:%S").replace(tzinfo=UTC).timestamp()
    except ValueError:
        return None
    nanos = int((fraction + "000000000")[:9]) if fraction.isdigit() else 0
    return int(seconds) * 1_000_000_000 + nanos, text


def read_docker_output(
    name: str, position: dict[str, Any], *, service: bool, api: Any = None
) -> tuple[list[Output], dict[str, Any]]:
    """Return what a container (or Swarm service) printed after ``position``, both streams in time order."""
    api = api or _docker_api()
    since_ns = int(position.get("since_ns", 0))
    # Docker stamps each stream's lines as its own reader gets them: a line of one stream may reach the
    # log a moment after a later-stamped line of the other. Lines younger than this wait for the next round,
    # so the newest timestamp collected never passes a line still on its way.
    settled_ns = time.time_ns() - SETTLE_NS
    found: list[tuple[int, str, str]] = []
    for stream in ("stdout", "stderr"):
        options: dict[str, Any] = {"stdout": stream == "stdout", "stderr": stream == "stderr", "timestamps": True}
        if since_ns:
            options["since"] = since_ns // 1_000_000_000  # whole seconds: the rest is filtered below
        raw = api.service_logs(name, **options) if service else api.logs(name, **options)
        if not isinstance(raw, bytes | str):
            raw = b"".join(raw)
        text = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else raw
        for row in text.splitlines():
            parsed = parse_docker_line(row)
            if parsed is not None and since_ns < parsed[0] <= settled_ns:
                found.append((parsed[0], stream, parsed[1]))
    found.sort(key=lambda item: item[0])
    found = found[:MAX_LOG_LINES_PER_FRAME]
    lines = [(ns / 1e9, stream, _cut(text)) for ns, stream, text in found]
    return lines, {"since_ns": found[-1][0] if found else since_ns}


# --------------------------------------------------------------------------- collecting


def read_output(
    runtime: str, robot: str, skill: str, component: str, position: dict[str, Any]
) -> tuple[list[Output], dict[str, Any]]:
    """Read a copy's new output from the runtime it runs on."""
    if runtime == "process":
        return read_process_output(process_log_path(robot, skill, component), position)
    try:
        return read_docker_output(object_name(robot, skill, component), position, service=runtime == "swarm")
    except Exception as exc:
        if getattr(getattr(exc, "response", None), "status_code", None) == 404:
            return [], position  # not created yet, or removed: nothing to read
        raise


def collect_copy(runtime: str, robot: str, skill: str, component: str) -> int:
    """Store what one cloud copy printed since its cursor; return the lines stored."""
    with transaction.atomic():
        CloudLogCursor.objects.get_or_create(robot_id=robot, skill=skill, component=component)
        cursor = (
            CloudLogCursor.objects.select_for_update(skip_locked=True)
            .filter(robot_id=robot, skill=skill, component=component)
            .first()
        )
        if cursor is None:
            return 0  # another worker collects it right now
        output, position = read_output(runtime, robot, skill, component, cursor.position)
        stored = 0
        for start in range(0, len(output), MAX_LOG_LINES_PER_FRAME):
            chunk = output[start : start + MAX_LOG_LINES_PER_FRAME]
            lines = [
                {"seq": cursor.seq + n + 1, "ts": ts, "stream": stream, "level": parse_level(text), "text": text}
                for n, (ts, stream, text) in enumerate(chunk)
            ]
            stored += store_lines(robot, skill, component, "cloud", lines)
            cursor.seq += len(chunk)
        if position != cursor.position or output:
            cursor.position = position
            cursor.save(update_fields=["seq", "position"])
    return stored


def collect_all() -> int:
    """Collect the output of every copy the cloud should run now; return the lines stored."""
    runtime = runtime_name()
    copies = CloudInstance.objects.filter(desired=CloudInstance.Desired.RUNNING).values_list(
        "component__skill__robot_id", "component__skill__skill_id", "component__component_id"
    )
    stored = 0
    for robot, skill, component in copies:
        try:
            stored += collect_copy(runtime, robot, skill, component)
        except Exception:
            # One copy's engine trouble must not keep the others' lines from being collected.
            log.warning("collecting the output of %s/%s/%s failed", robot, skill, component, exc_info=True)
    return stored


def crash_lines(robot: str, skill: str, component: str) -> list[dict[str, Any]]:
    """Collect a crashed copy's last output, then return its last lines as LogLine dicts, oldest first."""
    try:
        collect_copy(runtime_name(), robot, skill, component)
    except Exception:
        # The crash is recorded anyway, with the lines collected before.
        log.warning("collecting the last output of %s/%s/%s failed", robot, skill, component, exc_info=True)
    return [line_dict(row) for row in tail_lines(robot, skill, component, "cloud", CRASH_LOG_LINES)]
