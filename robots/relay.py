"""Relay commands to robots through their consumers, on whichever server process holds each, and collect replies.

One robot or ten thousand take the same path: their channels are read in one query, the commands
go out a window at a time, and every reply comes back on one reply channel, matched by the
command's id. Robots served by this process are reached directly (robots.local), the others
through the channel layer. A fleet-wide command used to open a reply channel, a
database query and a Redis connection per robot, and ran out of Redis connections at 3,000 robots.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

from asgiref.sync import sync_to_async
from channels.layers import get_channel_layer

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Envelope, Event
from monitoring import prometheus

from .local import deliver, local_consumer, register_local, unregister_local
from .models import Robot

# Commands in flight at once: their replies queue on one channel, whose capacity (CHANNEL_LAYER_CAPACITY,
# 5,000) a whole fleet answering at once would overflow; and each send takes a Redis connection.
WINDOW = 500


class RobotOffline(Exception):
    """The robot is not connected, so a command cannot reach it."""


class CommandTimeout(Exception):
    """The robot did not answer a command in time."""


def robot_channels(robot_ids: list[str]) -> dict[str, str]:
    """Return the consumer channel of each of these robots that is connected."""
    rows = Robot.objects.filter(id__in=robot_ids, connected=True).exclude(channel="").values_list("id", "channel")
    return dict(rows)


class Replies:
    """The reply channel of one relay: fed directly by the consumers of this process, or by the channel layer."""

    def __init__(self, layer: Any, channel_name: str) -> None:
        self.layer = layer
        self.channel_name = channel_name
        self.here: asyncio.Queue[dict] = asyncio.Queue()
        self._here_get: asyncio.Future | None = None
        self._remote: asyncio.Future | None = None
        register_local(self)

    async def dispatch(self, message: dict) -> None:
        """Take a reply from a consumer of this process (robots.local.deliver)."""
        self.here.put_nowait(message)

    async def next_within(self, seconds: float, *, remote: bool) -> list[dict]:
        """Return the replies that came, waiting at most ``seconds`` for the first; [] once they have passed.

        The channel layer is read only when ``remote`` (a robot on another process), by one receive kept
        across calls and given up at the end, never cancelled in place: with several commands waiting in
        one process, channels-redis's receive (4.3) was seen to absorb its cancellation and run on, and
        its command waited until the robot left (409 after a minute) instead of answering 504 after its
        wait. A given-up receive ends with the next message.
        """
        if not self.here.empty():
            return self._drain_here()
        if self._here_get is None:
            self._here_get = asyncio.ensure_future(self.here.get())
        if remote and self._remote is None:
            self._remote = asyncio.ensure_future(self.layer.receive(self.channel_name))
        waiting = {future for future in (self._here_get, self._remote) if future is not None}
        done, _ = await asyncio.wait(waiting, timeout=seconds, return_when=asyncio.FIRST_COMPLETED)
        messages = []
        if self._remote in done:
            messages.append(self._remote.result())
            self._remote = None
        if self._here_get in done:
            messages.append(self._here_get.result())
            self._here_get = None
            messages.extend(self._drain_here())
        return messages

    def _drain_here(self) -> list[dict]:
        messages = []
        while not self.here.empty():
            messages.append(self.here.get_nowait())
        return messages

    def close(self) -> None:
        """Stop taking replies; a receive still waiting on the channel layer is given up."""
        unregister_local(self)
        if self._here_get is not None:
            self._here_get.cancel()
        if self._remote is not None:
            self._remote.cancel()
            self._remote.add_done_callback(_forget)


def _forget(task: asyncio.Future) -> None:
    """Retrieve a given-up receive's outcome so asyncio does not report it as never retrieved."""
    if not task.cancelled():
        task.exception()


async def relay_command(robot_id: str, event: Event | str, data: dict[str, Any], *, wait: float = 5.0) -> Envelope:
    """Send a command to a robot through its consumer and return the robot's reply.

    Raises ProtocolError for a malformed command, RobotOffline when the robot is not
    connected and CommandTimeout when no reply came within ``wait`` seconds.
    """
    outcome = (await relay_to_many([robot_id], event, data, wait=wait))[robot_id]
    if isinstance(outcome, Exception):
        raise outcome
    return outcome


async def relay_to_many(
    robot_ids: list[str], event: Event | str, data: dict[str, Any], *, wait: float = 5.0
) -> dict[str, Envelope | RobotOffline | CommandTimeout]:
    """Send one command to every robot named and return each one's reply, RobotOffline or CommandTimeout.

    Raises ProtocolError for a malformed command before anything is sent. ``wait`` bounds the whole
    relay: a robot that has not answered when it runs out gets CommandTimeout.
    """
    started = time.monotonic()
    deadline = started + wait
    protocol.make(event, data, now=time.time())  # a malformed command fails here, for every robot at once
    channels = await sync_to_async(robot_channels)(list(robot_ids))
    outcomes: dict[str, Envelope | RobotOffline | CommandTimeout] = {}
    for robot_id in robot_ids:
        if robot_id not in channels:
            outcomes[robot_id] = RobotOffline(robot_id)
            prometheus.command_finished("offline", started)
    if not channels:
        return outcomes
    layer = get_channel_layer()
    # The default prefix matters: channels-redis reads all of a process's channels of one prefix
    # in one loop, and a second prefix would wait behind that loop's blocking read.
    replies = Replies(layer, await layer.new_channel())
    # Robots served by this process get the command, and answer it, without the channel layer:
    # a fleet-wide command was four Redis round trips a robot, 300 robots a second.
    remote = any(local_consumer(channel) is None for channel in channels.values())
    waiting: dict[str, str] = {}  # command id -> robot
    queue = list(channels.items())

    async def send_one(robot_id: str, channel: str) -> None:
        envelope = protocol.make(event, data, now=time.time())
        waiting[envelope.id] = robot_id
        message = {"type": "robot.command", "id": envelope.id, "frame": protocol.encode(envelope)}
        await deliver(channel, {**message, "reply_channel": replies.channel_name})

    try:
        while queue or waiting:
            room = WINDOW - len(waiting)
            if queue and room > 0:
                batch, queue = queue[:room], queue[room:]
                await asyncio.gather(*(send_one(robot_id, channel) for robot_id, channel in batch))
            left = deadline - time.monotonic()
            if left <= 0:
                break
            messages = await replies.next_within(left, remote=remote)
            if not messages:
                break
            for message in messages:
                reply = None if message.get("offline") else protocol.decode(message["frame"])
                robot_id = waiting.pop(str((reply.reply_to if reply else message.get("id")) or ""), "")
                if not robot_id:
                    continue  # an answer after its robot was given up, or an old robot's goodbye without an id
                if reply is None:
                    outcomes[robot_id] = RobotOffline(robot_id)
                    prometheus.command_finished("offline", started)
                else:
                    outcomes[robot_id] = reply
                    prometheus.command_finished(
                        "refused" if reply.event == Event.ERROR_MESSAGE else "accepted", started
                    )
    finally:
        replies.close()
    for robot_id in [*waiting.values(), *(robot_id for robot_id, _ in queue)]:
        outcomes[robot_id] = CommandTimeout(f"robot {robot_id} did not answer {event} within {wait:g} s")
        prometheus.command_finished("timeout", started)
    return outcomes
