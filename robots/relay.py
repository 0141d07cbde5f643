"""Relay commands to robots through their consumers, on whichever server process holds each, and collect replies.

One robot or ten thousand take the same path: their channels are read in one query, the commands
go out through the channel layer a window at a time, and every reply comes back on one reply
channel, matched by the command's id. A fleet-wide command used to open a reply channel, a
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


async def receive_within(layer: Any, channel: str, seconds: float) -> dict | None:
    """Return the next message on a reply channel, or None once ``seconds`` have passed.

    The receive runs as a task of its own that is given up at the deadline, not cancelled in place:
    with several commands waiting in one process, channels-redis's receive (4.3) was seen to absorb
    its cancellation and run on, and its command waited until the robot left (409 after a minute)
    instead of answering 504 after its wait. A given-up receive ends with the next message.
    """
    receiving = asyncio.ensure_future(layer.receive(channel))
    done, _ = await asyncio.wait({receiving}, timeout=seconds)
    if receiving in done:
        return receiving.result()
    receiving.cancel()
    receiving.add_done_callback(_forget)
    return None


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
    reply_channel = await layer.new_channel()
    waiting: dict[str, str] = {}  # command id -> robot
    queue = list(channels.items())

    async def send_one(robot_id: str, channel: str) -> None:
        envelope = protocol.make(event, data, now=time.time())
        waiting[envelope.id] = robot_id
        message = {"type": "robot.command", "id": envelope.id, "frame": protocol.encode(envelope)}
        await layer.send(channel, {**message, "reply_channel": reply_channel})

    while queue or waiting:
        room = WINDOW - len(waiting)
        if queue and room > 0:
            batch, queue = queue[:room], queue[room:]
            await asyncio.gather(*(send_one(robot_id, channel) for robot_id, channel in batch))
        left = deadline - time.monotonic()
        if left <= 0:
            break
        message = await receive_within(layer, reply_channel, left)
        if message is None:
            break
        reply = None if message.get("offline") else protocol.decode(message["frame"])
        robot_id = waiting.pop(str((reply.reply_to if reply else message.get("id")) or ""), "")
        if not robot_id:
            continue  # an answer after its robot was given up, or an old robot's goodbye without an id
        if reply is None:
            outcomes[robot_id] = RobotOffline(robot_id)
            prometheus.command_finished("offline", started)
        else:
            outcomes[robot_id] = reply
            prometheus.command_finished("refused" if reply.event == Event.ERROR_MESSAGE else "accepted", started)
    for robot_id in [*waiting.values(), *(robot_id for robot_id, _ in queue)]:
        outcomes[robot_id] = CommandTimeout(f"robot {robot_id} did not answer {event} within {wait:g} s")
        prometheus.command_finished("timeout", started)
    return outcomes
