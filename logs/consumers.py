"""The robot door's handler of component logs: a robot ships its own components' lines."""

from __future__ import annotations

import logging
from typing import Any

from bridgeos_agent.protocol import Envelope, Event
from robots.consumers import RobotConsumer, handles, sync
from robots.dedup import applied_ids

from . import services

log = logging.getLogger(__name__)


@handles(Event.COMPONENT_LOGS)
async def on_component_logs(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    """Store a frame of lines beside the door's path, acked once stored.

    Awaited in line, a flood's 5,000-line frames held the robot's next frames (its metrics) back
    behind every insert: metrics lagged 7x under a 25,000 lines/s flood. The robot keeps at most
    two log frames unacked, so a robot never has more than two stores under way.
    """

    async def store() -> None:
        try:
            # Always the socket's robot: a robot speaks only for itself (the door refuses another data.robot).
            # Also a robot's answer to component_logs_get, which the door has handed to its requester already.
            await sync(services.store_lines)(consumer.robot_id, p.skill, p.component, p.location, p.lines, p.dropped)
        except Exception:
            consumer.dedup.forget(envelope.id)
            log.exception("robot %s: storing component logs failed", consumer.robot_id)
            await consumer.fail("lines not stored, send again later", reply_to=envelope.id, code="unavailable")
            return
        applied_ids().add(consumer.robot_id, envelope.id)
        await consumer.ack_applied(envelope)

    consumer.spawn(store())
    return False
