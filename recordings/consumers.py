"""The robot door's handlers of recordings: each chunk kept before it is acked, each status applied."""

from __future__ import annotations

import base64
import binascii
from typing import Any

from django.core.exceptions import ValidationError

from bridgeos_agent.protocol import Envelope, Event
from robots.consumers import RobotConsumer, handles, sync

from . import services


@handles(Event.RECORDING_CHUNK)
async def on_recording_chunk(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    try:
        data = base64.b64decode(p.data, validate=True)
    except binascii.Error:
        raise ValidationError({"data": ["Not base64."]}) from None
    await sync(services.store_recording_chunk)(consumer.robot_id, p.recording, p.seq, data)
    return True


@handles(Event.RECORDING_STATUS)
async def on_recording_status(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await sync(services.report_recording_status)(consumer.robot_id, p)
    return True
