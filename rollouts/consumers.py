"""The robot door's handler of rollouts: a component's update hold, applied as the owner's would be."""

from __future__ import annotations

from typing import Any

from bridgeos_agent.protocol import Envelope, Event
from robots.consumers import RobotConsumer, handles, sync

from . import rolling


@handles(Event.UPDATE_HOLD)
async def on_update_hold(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(rolling.component_hold)(consumer.robot_id, p.skill, p.component, p.seconds, p.reason)
    return True
