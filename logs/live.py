"""Live tails: stored lines pushed to the clients subscribed to their robot, a robot's lines of ~0.1 s in one message.

A `group_send` per frame caps a consumer at under 1,000 frames/s (see monitoring.live), so a
process gathers the lines committed on its loop and sends them to each robot's group
(`logs.<robot>`) once per interval, every component's lines already JSON-encoded once for all
subscribers. Code without a loop (a Celery worker collecting cloud copies' output) sends each
call's lines as one message: a call carries a batch already.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
from typing import TYPE_CHECKING, Any

from asgiref.sync import SyncToAsync
from channels.layers import BaseChannelLayer, get_channel_layer
from django.db import transaction

from bridgeos_agent.logonce import LogOnce
from bridgeos_cloud.layersync import layer_sync
from bridgeos_cloud.loopowned import loop_object

if TYPE_CHECKING:
    from bridgeos_agent.protocol import LogLine

logger = logging.getLogger(__name__)

# Frames to clients stay well under the protocol's 1 MiB: a component's lines are cut into several past this.
FRAME_TEXT_BYTES = 512 * 1024
FLUSH_INTERVAL_S = 0.1

# One component's new lines: (skill, component, location, line dicts, dropped).
Batch = tuple[str, str, str, list[dict[str, Any]], int]


def group_name(robot_id: str) -> str:
    """Return the channel group of a robot's live tails."""
    return f"logs.{robot_id}"


def frames_data(
    robot_id: str, skill: str, component: str, location: str, lines: list[dict[str, Any]], dropped: int
) -> list[str]:
    """Encode `component_logs` data for clients (several when the lines are many or long), oldest lines first."""
    frames, chunk, size = [], [], 0
    for line in lines:
        size += len(line["text"]) * 4 + 100  # at worst 4 bytes a character in JSON, and the line's other fields
        chunk.append(line)
        if size >= FRAME_TEXT_BYTES:
            frames.append(chunk)
            chunk, size = [], 0
    if chunk or not frames:
        frames.append(chunk)
    head = {"robot": robot_id, "skill": skill, "component": component, "location": location}
    # The drop count goes with the last frame: the lines it precedes arrived before it was counted.
    return [
        json.dumps({**head, "lines": chunk, "dropped": dropped if n == len(frames) - 1 else 0}, separators=(",", ":"))
        for n, chunk in enumerate(frames)
    ]


def line_dicts(lines: list[LogLine]) -> list[dict[str, Any]]:
    """Return LogLines as the dicts frames carry."""
    return [
        {"seq": line.seq, "ts": line.ts, "stream": line.stream, "level": line.level, "text": line.text}
        for line in lines
    ]


def message_of(robot_id: str, batches: list[Batch]) -> dict[str, Any]:
    """Return the group message of a robot's batches, the lines of one component merged in order."""
    merged: dict[tuple[str, str, str], tuple[list[dict[str, Any]], int]] = {}
    for skill, component, location, lines, dropped in batches:
        known, count = merged.get((skill, component, location), ([], 0))
        merged[(skill, component, location)] = (known + lines, count + dropped)
    frames = []
    for (skill, component, location), (lines, dropped) in merged.items():
        lines.sort(key=lambda line: line["seq"])
        for data in frames_data(robot_id, skill, component, location, lines, dropped):
            frames.append([skill, component, data])
    return {"type": "logs.lines", "robot": robot_id, "frames": frames}


class LogFeed:
    """Gather committed lines per robot and send them to its tails' group once per interval."""

    def __init__(self, *, interval: float = FLUSH_INTERVAL_S, layer: BaseChannelLayer | None = None) -> None:
        self.interval = interval
        self.layer = layer
        self.messages_sent = 0
        self._pending: dict[str, list[Batch]] = {}
        self._task: asyncio.Task[None] | None = None
        self._failures = LogOnce(logger, "Sending live log lines", traceback=True)

    def add(self, robot_id: str, batch: Batch) -> None:
        """Queue one component's new lines; they go out within the interval."""
        self._pending.setdefault(robot_id, []).append(batch)
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run(), name="live-logs")

    async def send(self) -> None:
        """Send what is pending now, one message per robot."""
        pending, self._pending = self._pending, {}
        layer = self.layer or get_channel_layer()
        if layer is None:
            return
        for robot_id, batches in pending.items():
            await layer.group_send(group_name(robot_id), message_of(robot_id, batches))
            self.messages_sent += 1

    async def _run(self) -> None:
        try:
            while self._pending:
                await asyncio.sleep(self.interval)
                try:
                    await self.send()
                except Exception as exc:
                    # Live lines are expendable: they are stored, and a tail reads them again when it resubscribes.
                    self._failures.failed(exc)
                else:
                    self._failures.worked()
        finally:
            self._task = None

    async def close(self) -> None:
        """Send what is still pending."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        await self.send()


def get_log_feed() -> LogFeed:
    """Return this event loop's log feed; its owner closes it at shutdown."""
    return loop_object("live log feed", LogFeed)


async def _send_now(robot_id: str, batch: Batch) -> None:
    layer = get_channel_layer()
    if layer is not None:
        await layer.group_send(group_name(robot_id), message_of(robot_id, [batch]))


def _post(robot_id: str, batch: Batch) -> None:
    loop = getattr(SyncToAsync.threadlocal, "main_event_loop", None)
    if loop is not None and loop.is_running():
        # A consumer's database thread: daphne's loop gathers them and sends soon.
        loop.call_soon_threadsafe(lambda: get_log_feed().add(robot_id, batch))
        return
    layer_sync(_send_now)(robot_id, batch)


def publish_lines_on_commit(
    robot_id: str, skill: str, component: str, location: str, lines: list[LogLine], dropped: int
) -> None:
    """Push a component's newly stored lines to its robot's live tails once the transaction commits."""
    batch: Batch = (skill, component, location, line_dicts(lines), dropped)

    def send() -> None:
        _post(robot_id, batch)

    transaction.on_commit(send, robust=True)
