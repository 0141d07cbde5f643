"""The robot door's handler of component logs: a robot ships its own components' lines."""

from __future__ import annotations

from typing import Any

from bridgeos_agent.protocol import Envelope, Event
from robots.consumers import RobotConsumer, handles, sync

from . import services


@handles(Event.COMPONENT_LOGS)
async def on_component_logs(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    # Always the socket's robot: a robot speaks only for itself (the door refuses another data.robot).
    # Also a robot's answer to component_logs_get, which the door has handed to its requester already.
    await sync(services.store_lines)(consumer.robot_id, p.skill, p.component, p.location, p.lines, p.dropped)
    return True
