"""Make one component's cloud copy what its row wants: start it, or remove it."""

from __future__ import annotations

import logging
from typing import Any

from django.conf import settings
from django.db import transaction
from django.utils import timezone

from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import Event
from bridgeos_agent.runtime.base import ComponentState, RuntimeFailure, Status
from monitoring.services import record_event
from robots.services import hold_robot

from ..models import CloudInstance, Component
from .locks import LockBusy, orchestration_lock
from .orchestration import (
    LOG_TAIL,
    RUNNING,
    LaunchFailed,
    TryAgain,
    cloud_spec,
    cloud_subnet,
    instance_row,
    unreachable,
    who,
    with_runtime,
)
from .reporting import announce, fail, info_data, record_running, set_status
from .runtime import (
    CloudRuntime,
    EngineBusy,
)

logger = logging.getLogger(__name__)


def converge(instance_id: int, token: str | None = None) -> str:
    """Make one component's cloud copy what its row wants; return what was done."""
    try:
        with orchestration_lock(f"instance:{instance_id}"):
            instance = instance_row(instance_id)
            if instance is None:
                return "gone"
            if token is not None and instance.token != token:
                return "superseded"
            if instance.desired == RUNNING:
                return run_copy(instance)
            return stop_copy(instance)
    except LockBusy as exc:
        raise TryAgain(str(exc)) from None


def give_up(instance_id: int, token: str, reason: str) -> None:
    """Roll a start back for good: remove what runs, mark it failed, tell the robot why."""
    with orchestration_lock(f"instance:{instance_id}"):
        instance = instance_row(instance_id)
        if instance is None or instance.token != token:
            return
        fail(instance, reason)


def run_copy(instance: CloudInstance) -> str:
    """Start the copy (or adopt the one that runs), wait until it runs, and report it."""
    robot_id, skill_id, component_id = who(instance)
    try:
        spec = cloud_spec(instance)
        subnet = cloud_subnet(instance.component.skill.robot)
    except LaunchFailed as exc:
        fail(instance, str(exc))
        return "failed"
    if instance.status not in (CS.STARTING, CS.RUNNING):
        set_status(instance, CS.STARTING)
    timeout = settings.BRIDGEOS["CLOUD_START_TIMEOUT_S"]

    async def launch(runtime: CloudRuntime) -> tuple[ComponentState, dict[str, Any], list[str]]:
        runtime.subnet = subnet
        state = await runtime.start(spec)
        if state.status is not Status.RUNNING:
            state = await runtime.wait_running(skill_id, component_id, timeout)
        if state.status is Status.RUNNING:
            return state, await runtime.endpoint(spec), []
        return state, {}, await runtime.logs(skill_id, component_id, LOG_TAIL)

    try:
        state, endpoint, logs = with_runtime(robot_id, launch)
    except RuntimeFailure as exc:
        if unreachable(exc) or isinstance(exc, EngineBusy):
            raise TryAgain(str(exc)) from None
        fail(instance, str(exc))
        return "failed"
    if state.status is not Status.RUNNING:
        if not CloudInstance.objects.filter(pk=instance.pk, desired=RUNNING).exists():
            return stop_copy(instance)  # removed because it was stopped while it started: no failure
        reason = state.message or f"it ended at once (exit code {state.exit_code})"
        fail(instance, f"component {component_id} did not start in the cloud: {reason}", logs=logs)
        return "failed"
    if not record_running(instance, endpoint):
        return stop_copy(instance)  # stopped while it started (a stop request, cloud_down)
    return "running"


def stop_copy(instance: CloudInstance) -> str:
    """Remove the copy and record that it is stopped."""
    robot_id, skill_id, component_id = who(instance)
    try:
        with_runtime(robot_id, lambda runtime: runtime.stop(skill_id, component_id))
    except RuntimeFailure as exc:
        raise TryAgain(str(exc)) from None
    with transaction.atomic():
        if not hold_robot(robot_id):
            return "gone"  # its robot was deleted meanwhile, with the copy's rows
        CloudInstance.objects.filter(pk=instance.pk).update(
            status=CS.STOPPED, container={}, restart_at=None, updated_at=timezone.now()
        )
        component = Component.objects.select_for_update().filter(pk=instance.component_id).first()
        if component is None:
            return "gone"  # deleted meanwhile (its Skill or robot was removed)
        if "cloud" in component.container:
            component.container = {k: v for k, v in component.container.items() if k != "cloud"}
            component.save(update_fields=["container", "updated_at"])
        record_event(
            f"Cloud copy of {component_id} stopped",
            robot_id=robot_id,
            kind="cloud_component_stopped",
            skill=skill_id,
            component=component_id,
        )
        announce(robot_id, Event.COMPONENT_INFORMATION, info_data(skill_id, component_id, {}))
    return "stopped"
