"""A client's live tails over /ws/client/: logs_subscribe, logs_unsubscribe and the pushed lines.

Owned by one ClientConsumer, which has already checked the client holds the read right on the
robot. Subscribing joins the robot's group (`logs.<robot>`) before the backlog is read, so no
line committed in between is missed (one may come twice: its seq tells).
"""

from __future__ import annotations

import json
import logging
import time
from typing import TYPE_CHECKING, Any

from channels.db import database_sync_to_async
from django.conf import settings

from bridgeos_agent import protocol
from bridgeos_agent.protocol import MAX_LOG_LINES_PER_FRAME, Envelope, Event
from robots import services as robots

from . import services
from .live import frames_data, group_name

if TYPE_CHECKING:
    from dashboard.consumers import ClientConsumer

log = logging.getLogger(__name__)

# (skill, component) a client follows; None: every one.
Subscription = tuple[str | None, str | None]


def frame_text(data: str, reply_to: str | None) -> str:
    """Return a `component_logs` frame around already encoded data."""
    return (
        f'{{"event":"{Event.COMPONENT_LOGS}","id":"{protocol.new_id()}","reply_to":{json.dumps(reply_to)},'
        f'"data":{data},"ts":{time.time()!r}}}'
    )


def backlog(
    robot_id: str, skill: str | None, component: str | None, tail: int
) -> tuple[list[str], list[tuple[str, str]]]:
    """Return the encoded frames of the matching components' last lines, and the components matched."""
    components = services.known_components(robot_id, skill, component)
    if skill is not None and component is not None and (skill, component) not in components:
        components.append((skill, component))  # lines may be stored of a component its Skill no longer declares
    frames = []
    for skill_id, component_id in components:
        for location in ("robot", "cloud"):
            rows = services.tail_lines(robot_id, skill_id, component_id, location, tail)
            if rows:
                lines = [services.line_dict(row) for row in rows]
                frames.extend(frames_data(robot_id, skill_id, component_id, location, lines, 0))
    return frames, components


def matches(subscriptions: set[Subscription], skill: str, component: str) -> bool:
    """Tell whether a component's lines are followed by one of the subscriptions."""
    return any(
        (wanted_skill is None or wanted_skill == skill) and (wanted_component is None or wanted_component == component)
        for wanted_skill, wanted_component in subscriptions
    )


class LogTail:
    """The live tails of one client connection."""

    def __init__(self, consumer: ClientConsumer) -> None:
        self.consumer = consumer
        self.subscriptions: dict[str, set[Subscription]] = {}

    async def handle(self, envelope: Envelope, robot_id: str, payload: Any) -> None:
        """Serve logs_subscribe or logs_unsubscribe (the client may read the robot)."""
        if envelope.event == Event.LOGS_SUBSCRIBE:
            await self.subscribe(envelope, robot_id, payload)
        else:
            await self.unsubscribe(envelope, robot_id, payload)

    async def subscribe(self, envelope: Envelope, robot_id: str, p: Any) -> None:
        """Follow a robot, Skill or component: answer its last lines, then push new ones."""
        consumer = self.consumer
        if robot_id not in self.subscriptions:
            await consumer.channel_layer.group_add(group_name(robot_id), consumer.channel_name)
        self.subscriptions.setdefault(robot_id, set()).add((p.skill, p.component))
        frames, components = await database_sync_to_async(backlog)(robot_id, p.skill, p.component, p.tail)
        if not frames and p.component is not None:
            frames = frames_data(robot_id, p.skill, p.component, "robot", [], 0)
        if not frames:
            await consumer.ack(envelope)
        for data in frames:
            await consumer.send_text(frame_text(data, envelope.id))
        if p.ring:
            for skill_id, component_id in components:
                await self.ask_ring(robot_id, skill_id, component_id)

    async def ask_ring(self, robot_id: str, skill: str, component: str) -> None:
        """Ask the robot for its ring's lines the cloud never got; the robot door stores them, and they are pushed."""
        after = await database_sync_to_async(services.newest_seq)(robot_id, skill, component, "robot")
        data = {"skill": skill, "component": component, "after_seq": after, "limit": MAX_LOG_LINES_PER_FRAME}
        try:
            reply = await robots.relay_command(
                robot_id, Event.COMPONENT_LOGS_GET, data, wait=settings.BRIDGEOS["COMMAND_WAIT_S"]
            )
        except (robots.RobotOffline, robots.CommandTimeout) as exc:
            # The ring is a best effort on top of what is stored: the tail goes on without it.
            log.info("robot %s: no ring lines of %s/%s: %s", robot_id, skill, component, exc)
            return
        if reply.event == Event.ERROR_MESSAGE:
            log.info("robot %s refused its ring of %s/%s: %s", robot_id, skill, component, reply.data)

    async def unsubscribe(self, envelope: Envelope, robot_id: str, p: Any) -> None:
        """Stop following what a logs_subscribe with the same robot, skill and component followed."""
        subscriptions = self.subscriptions.get(robot_id)
        if subscriptions is not None:
            subscriptions.discard((p.skill, p.component))
            if not subscriptions:
                await self.leave(robot_id)
        await self.consumer.ack(envelope)

    async def leave(self, robot_id: str) -> None:
        """Stop hearing a robot's lines."""
        self.subscriptions.pop(robot_id, None)
        await self.consumer.channel_layer.group_discard(group_name(robot_id), self.consumer.channel_name)

    async def close(self) -> None:
        """Leave every robot's group (the socket closed)."""
        for robot_id in list(self.subscriptions):
            await self.leave(robot_id)

    async def push(self, message: dict[str, Any]) -> None:
        """Pass on the new lines of components this client follows, while it may still see their robot."""
        robot_id = message["robot"]
        subscriptions = self.subscriptions.get(robot_id)
        if not subscriptions:
            return
        if not await self.consumer.sees(robot_id):
            await self.leave(robot_id)
            return
        for skill, component, data in message["frames"]:
            if matches(subscriptions, skill, component):
                await self.consumer.send_text(frame_text(data, None))
