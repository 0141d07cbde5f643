"""Answer the cloud's ~30 commands and reports to the robot: one handler per event, in a dispatch table.

A handler gets the controller, the frame and its validated payload. It returns ``(event, data)``
to answer with a frame, or None to ack; a ``ProtocolError`` becomes an ``error_message`` naming
the offending field.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable, Mapping
from typing import TYPE_CHECKING, Any

from pydantic import ValidationError

from bridgeos_agent import protocol
from bridgeos_agent.errors import field_errors
from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import Envelope, Event, ProtocolError
from bridgeos_agent.protocol import SkillStatusName as SS
from bridgeos_agent.robotconfig import RobotConfig, merge_config_changes, parse_robot_config
from bridgeos_agent.session import Reply
from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_agent.state import find_component, find_skill

if TYPE_CHECKING:
    from bridgeos_agent.controller import RobotController

__all__ = ["HANDLERS", "call_components_api", "dispatch", "handles"]

logger = logging.getLogger("bridgeos_agent")

Handler = Callable[["RobotController", Envelope, Any], Awaitable[Reply | None]]
HANDLERS: dict[str, Handler] = {}


def handles(*events: Event) -> Callable[[Handler], Handler]:
    """Register a handler of cloud frames; it returns (event, data) to reply, or None to ack."""

    def register(function: Handler) -> Handler:
        for event in events:
            HANDLERS[event] = function
        return function

    return register


async def dispatch(controller: RobotController, envelope: Envelope) -> Reply | None:
    """Run the handler of a frame from the cloud; ProtocolError if none applies."""
    handler = HANDLERS.get(envelope.event)
    if handler is None:
        raise ProtocolError(f"a robot does not handle {envelope.event}", code="unsupported")
    payload = protocol.parse_payload(envelope)
    if getattr(payload, "robot", None) not in (None, controller.settings.robot):
        raise ProtocolError("addressed to another robot", field="data.robot", code="forbidden")
    return await handler(controller, envelope, payload)


def _not_before_config(controller: RobotController) -> None:
    if not controller.config_from_cloud.is_set():
        raise ProtocolError("no robot config from the cloud yet; skills wait for one", code="invalid_state")


@handles(Event.ROBOT_CONFIG)
async def on_robot_config(controller: RobotController, envelope: Envelope, p: Any) -> None:
    try:
        config = parse_robot_config(dict(p.config))
    except ValueError as exc:
        raise ProtocolError(_first_error(exc), field="data.config", code="invalid_config") from None
    controller.apply_config(config, source="cloud")
    controller.session.resolve(envelope)


@handles(Event.ROBOT_CONFIG_UPDATE)
async def on_robot_config_update(controller: RobotController, envelope: Envelope, p: Any) -> None:
    base = (controller.config or RobotConfig()).model_dump(mode="json")
    try:
        config = parse_robot_config(merge_config_changes(base, p.changes))
    except ValueError as exc:
        raise ProtocolError(_first_error(exc), field="data.changes", code="invalid_config") from None
    controller.apply_config(config, source="cloud")


@handles(Event.ROBOT_REKEY)
async def on_robot_rekey(controller: RobotController, envelope: Envelope, p: Any) -> None:
    # Acked once kept: a write that fails is answered with an error, and the cloud logs it.
    await controller.rekey(p.token)


@handles(Event.OFFLOADING)
async def on_offloading(controller: RobotController, envelope: Envelope, p: Any) -> None:
    base = (controller.config or RobotConfig()).model_dump(mode="json")
    controller.apply_config(parse_robot_config({**base, "offloading": str(p.mode)}), source="cloud")


@handles(Event.OFFLOADING_GET)
async def on_offloading_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    return Event.OFFLOADING, {"mode": (controller.config or RobotConfig()).offloading}


@handles(Event.SKILL_START)
async def on_skill_start(controller: RobotController, envelope: Envelope, p: Any) -> None:
    _not_before_config(controller)
    if p.config is None:
        record = find_skill(controller.skills, p.skill)
        config = record.config
    else:
        try:
            config = parse_skill_config(dict(p.config))
        except ValueError as exc:
            raise ProtocolError(_first_error(exc), field="data.config", code="invalid_config") from None
        if config.skill_id != p.skill:
            raise ProtocolError(
                f"config is for skill {config.skill_id!r}, not {p.skill!r}", field="data.config.skill_id"
            )
    if p.cloud_relay is not None:
        controller.cloud_relays[p.skill] = p.cloud_relay  # a Skill added since the login: its router links to it
    # Accepted: ack now, launch in the background and report progress as statuses.
    controller.spawn(controller.start_skill(config))


@handles(Event.SKILL_STOP)
async def on_skill_stop(controller: RobotController, envelope: Envelope, p: Any) -> None:
    find_skill(controller.skills, p.skill)
    controller.spawn(controller.stop_skill(p.skill))


@handles(Event.SKILL_STATUS_GET)
async def on_skill_status_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    return Event.SKILL_STATUS, {"skill": p.skill, "status": str(find_skill(controller.skills, p.skill).status)}


@handles(Event.SKILL_CONFIG)
async def on_skill_config(controller: RobotController, envelope: Envelope, p: Any) -> None:
    if controller.session.resolve(envelope):
        return  # the answer to a request (a restart asking for its latest config)
    try:
        config = parse_skill_config(dict(p.config))
    except ValueError as exc:
        raise ProtocolError(_first_error(exc), field="data.config", code="invalid_config") from None
    record = controller.skills.get(p.skill)
    if record is not None and record.status not in (SS.RUNNING, SS.STARTING):
        record.config = config
    # A Skill just added, or a release on its way (installed later, or held): its images come now, so
    # its start does not wait for bytes. A running version keeps its config until it is restarted.
    images = getattr(controller.runtime, "images", None)
    if images is not None:
        wanted: dict[str, list[str]] = {}
        for name, component in config.components.items():
            if component.location != "cloud" and component.robot is not None and component.robot.image:
                wanted.setdefault(component.robot.image, []).append(name)
        if wanted:
            controller.spawn(images.prefetch(p.skill, wanted, getattr(controller.runtime, "on_pull", None)))


@handles(Event.COMPONENT_START)
async def on_component_start(controller: RobotController, envelope: Envelope, p: Any) -> None:
    _not_before_config(controller)
    record = find_component(controller.skills, p.skill, p.component)
    await controller.place_component(record, p.component, location=str(p.location))


@handles(Event.COMPONENT_STOP)
async def on_component_stop(controller: RobotController, envelope: Envelope, p: Any) -> None:
    record = find_component(controller.skills, p.skill, p.component)
    await controller.placement.stop_component(record, p.component, only=str(p.location) if p.location else None)


@handles(Event.COMPONENT_MIGRATE)
async def on_component_migrate(controller: RobotController, envelope: Envelope, p: Any) -> None:
    _not_before_config(controller)
    record = find_component(controller.skills, p.skill, p.component)
    await controller.migrate_component(record, p.component, str(p.location) if p.location else None)


@handles(Event.COMPONENT_STATUS)
async def on_component_status(controller: RobotController, envelope: Envelope, p: Any) -> None:
    # The cloud reports its copy of a component (started, restarting after a crash, failed).
    if p.location == "cloud" and p.skill in controller.skills:
        controller.placement.on_cloud_report(p.skill, p.component, str(p.status), p.message)


@handles(Event.COMPONENT_INFORMATION)
async def on_component_information(controller: RobotController, envelope: Envelope, p: Any) -> None:
    # Where an instance is reached (the cloud sends its copies' address and published ports): kept for
    # the Skill Router's HTTP routes. A Skill or component this robot no longer has is ignored.
    record = controller.skills.get(p.skill)
    if record is None or p.component not in record.config.components:
        return
    container = p.container.model_dump(mode="json", exclude_none=True)
    if p.location == "cloud":
        record.cloud_containers[p.component] = container
    router = record.context("router")
    if router is not None:
        router.set_container(p.component, str(p.location), container)


@handles(Event.METRICS)
async def on_cloud_metrics(controller: RobotController, envelope: Envelope, p: Any) -> None:
    # The cloud's measurements of this robot's cloud copies, for each Skill's manager.
    by_skill: dict[str, list[dict[str, Any]]] = {}
    for point in p.metrics:
        skill, component = point.get("skill"), point.get("component")
        if skill and component:
            by_skill.setdefault(skill, []).append({key: value for key, value in point.items() if value is not None})
    for skill_id, points in by_skill.items():
        record = controller.skills.get(skill_id)
        manager = record.context("manager") if record is not None else None
        store = getattr(manager, "store", None)
        if store is not None:
            store.publish(points)


@handles(Event.VOLUME_CHANGES)
async def on_volume_changes(controller: RobotController, envelope: Envelope, p: Any) -> None:
    await controller.volumes.receive(p)


@handles(Event.VOLUME_CHUNKS_GET)
async def on_volume_chunks_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    return Event.VOLUME_CHUNKS, await controller.volumes.chunks(p)


@handles(Event.VOLUME_CHUNKS)
async def on_volume_chunks(controller: RobotController, envelope: Envelope, p: Any) -> None:
    controller.session.resolve(envelope)


@handles(Event.COMPONENT_STATUS_GET)
async def on_component_status_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    record = find_component(controller.skills, p.skill, p.component)
    data = {"skill": p.skill, "component": p.component, "status": str(record.statuses.get(p.component, CS.STOPPED))}
    if record.locations.get(p.component):
        data["location"] = record.locations[p.component]
    return Event.COMPONENT_STATUS, data


@handles(Event.COMPONENT_LOGS_GET)
async def on_component_logs_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    # Lines of the ring the cloud never received (a live tail asked for them): read, not shipped again.
    find_component(controller.skills, p.skill, p.component)
    return Event.COMPONENT_LOGS, await controller.logs.lines_after(p.skill, p.component, p.after_seq, p.limit)


@handles(Event.ROBOT_STOP)
async def on_robot_stop(controller: RobotController, envelope: Envelope, p: Any) -> None:
    for skill_id, record in list(controller.skills.items()):
        if record.status in (SS.RUNNING, SS.STARTING):
            controller.spawn(controller.stop_skill(skill_id))


@handles(Event.ROBOT_START)
async def on_robot_start(controller: RobotController, envelope: Envelope, p: Any) -> None:
    _not_before_config(controller)
    for record in list(controller.skills.values()):
        if record.status in (SS.STOPPED, SS.FAILED):
            controller.spawn(controller.start_skill(record.config))


@handles(Event.SHUTDOWN)
async def on_shutdown(controller: RobotController, envelope: Envelope, p: Any) -> None:
    async def shut_down() -> None:
        for skill_id in list(controller.skills):
            try:
                await controller.stop_skill(skill_id)
            except Exception:
                # Shutting down regardless; the operator reads why this Skill did not stop cleanly.
                logger.exception("shutdown: stopping skill %s failed", skill_id)
        await controller.emit(Event.SHUTDOWN, {"reason": p.reason or "ordered by the cloud"})
        await asyncio.sleep(0.5)  # let the report and its ack cross
        controller.stop(0)

    controller.spawn(shut_down())


@handles(Event.CONNECTION_ESTABLISHED)
async def on_connection_established(controller: RobotController, envelope: Envelope, p: Any) -> None:
    return None


@handles(Event.METRICS_GET)
async def on_metrics_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    latest = controller.monitor.latest
    now = time.time()
    values = latest.values if latest else {}
    names = set(p.names) if p.names else None
    points = [
        {"name": name, "value": float(value), "ts": now}
        for name, value in values.items()
        if names is None or name in names
    ]
    return Event.METRICS, {"metrics": points[: p.limit or len(points)]}


@handles(Event.RECORDING_START)
async def on_recording_start(controller: RobotController, envelope: Envelope, p: Any) -> None:
    await controller.recordings.start(p)


@handles(Event.RECORDING_STOP)
async def on_recording_stop(controller: RobotController, envelope: Envelope, p: Any) -> None:
    await controller.recordings.stop(p.recording)


@handles(Event.COMPONENTS_API)
async def on_components_api(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    record = controller.skills.get(p.skill)
    env = record.context("env") if record is not None else None
    url = env.get("BRIDGEOS_MANAGER_URL") if isinstance(env, dict) else None
    if not url:
        raise ProtocolError(f"skill {p.skill!r} runs no manager on this robot", field="data.skill", code="not_found")
    status, body = await call_components_api(url, p.method, p.path, p.query, p.body)
    return Event.COMPONENTS_API_REPLY, {"skill": p.skill, "status": status, "body": body}


async def call_components_api(
    base: str, method: str, path: str, query: str, body: Mapping[str, Any] | None
) -> tuple[int, Any]:
    """Call a Skill's Components API on this robot; return its status and JSON answer."""
    import aiohttp

    url = base.rstrip("/") + path + (f"?{query}" if query else "")
    timeout = aiohttp.ClientTimeout(total=10)
    async with aiohttp.ClientSession(timeout=timeout) as session, session.request(method, url, json=body) as answer:
        try:
            return answer.status, await answer.json(content_type=None)
        except ValueError:
            return answer.status, {"error": (await answer.text())[:2000]}


@handles(Event.BRIDGE_OPEN)
async def on_bridge_open(controller: RobotController, envelope: Envelope, p: Any) -> None:
    # Joining the graph takes a moment: the session starts in the background, its frames queue meanwhile.
    controller.bridges.open(p.session, p.kind, p.bytes_per_s, batches=p.batches, blobs=p.blobs)


@handles(Event.BRIDGE_FRAME)
async def on_bridge_frame(controller: RobotController, envelope: Envelope, p: Any) -> None:
    controller.bridges.receive(p)


@handles(Event.BRIDGE_CLOSE)
async def on_bridge_close(controller: RobotController, envelope: Envelope, p: Any) -> None:
    await controller.bridges.end(p.session)


def _first_error(exc: ValueError) -> str:
    errors = field_errors(exc) if isinstance(exc, ValidationError) else None
    if errors:
        path, messages = next(iter(errors.items()))
        return f"{path}: {messages[0]}" if path else messages[0]
    return str(exc).splitlines()[0]
