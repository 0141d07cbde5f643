"""The robot door's handlers of Skill volumes and of the cloud copies a robot asks for."""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from bridgeos_agent.protocol import Envelope, Event
from bridgeos_cloud.errors import NotFound
from robots.consumers import CHUNK_WAIT_S, RobotConsumer, handles, sync
from robots.dbthreads import AlreadyApplied
from robots.dedup import applied_ids

from . import services as skills
from .cloud.volumes import QuotaExceeded

log = logging.getLogger(__name__)


@handles(Event.VOLUME_CHANGES)
async def on_volume_changes(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    # Applied in the background (it asks the robot for chunks); acked once written.
    consumer.scan_volumes()

    async def apply() -> None:
        try:
            await consumer.volumes.receive(p, consumer.ask_chunks)
        except NotFound as exc:
            consumer.dedup.forget(envelope.id)
            await consumer.fail(exc.message, reply_to=envelope.id, field=exc.field, code="not_found")
        except QuotaExceeded as exc:
            consumer.dedup.forget(envelope.id)
            await consumer.fail(exc.message, reply_to=envelope.id, field=exc.field, code="quota_exceeded")
        except Exception as exc:
            consumer.dedup.forget(envelope.id)
            log.warning("robot %s: volume %s/%s not synced: %s", consumer.robot_id, p.skill, p.volume, exc)
            message = "volume changes not applied, send again later"
            await consumer.fail(message, reply_to=envelope.id, code="unavailable")
        else:
            applied_ids().add(consumer.robot_id, envelope.id)
            await consumer.ack_applied(envelope)

    writes = consumer.volume_writes.setdefault(p.skill, set())
    task = consumer.spawn(apply())
    writes.add(task)
    task.add_done_callback(writes.discard)
    return False


@handles(Event.VOLUME_CHUNKS_GET)
async def on_volume_chunks_get(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    await consumer.answer(envelope, Event.VOLUME_CHUNKS, await consumer.volumes.chunks(p))
    return False


@handles(Event.VOLUME_CHUNKS)
async def on_volume_chunks(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    # A late answer to a chunk request that timed out: nothing waits for it any more.
    return False


@handles(Event.COMPONENT_START, Event.COMPONENT_STOP)
async def on_cloud_component_request(consumer: RobotConsumer, envelope: Envelope, p: Any) -> bool:
    action = "start" if envelope.event == Event.COMPONENT_START else "stop"
    writes = consumer.volume_writes.setdefault(p.skill, set())
    if not writes:
        await sync(skills.request_cloud_component)(consumer.robot_id, p.skill, p.component, action)
        return True

    async def after_writes(earlier: list[asyncio.Future]) -> None:
        # A move to the cloud sends the Skill's volumes just before its start: the copy starts from
        # them. Waited for beside the frame loop, which goes on reading their chunks; a stop keeps its turn.
        await asyncio.wait(earlier, timeout=CHUNK_WAIT_S)
        try:
            await sync(skills.request_cloud_component)(consumer.robot_id, p.skill, p.component, action)
        except NotFound as exc:
            consumer.dedup.forget(envelope.id)
            await consumer.fail(exc.message, reply_to=envelope.id, field=exc.field, code="not_found")
            return
        except AlreadyApplied:
            pass  # an earlier copy asked for it
        applied_ids().add(consumer.robot_id, envelope.id)
        await consumer.ack_applied(envelope)

    task = consumer.spawn(after_writes(list(writes)))
    writes.add(task)
    task.add_done_callback(writes.discard)
    return False
