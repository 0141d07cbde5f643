"""Record what became of a cloud copy and tell the robot and the operators."""

from __future__ import annotations

import logging
from typing import Any

from django.db import transaction
from django.dispatch import Signal
from django.utils import timezone

from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import Event, Location
from bridgeos_agent.runtime.base import RuntimeFailure
from monitoring.choices import Level
from monitoring.live import publish_on_commit
from monitoring.services import record_event
from robots.services import client_frame, hold_robot, push_to_robot

from ..models import CloudInstance, Component
from .orchestration import LOG_TAIL, RUNNING, STOPPED, who, with_runtime

logger = logging.getLogger(__name__)

# Sent with robot_id=, skill=, component= when a cloud copy crashed or failed, before it is removed; a
# receiver may answer the copy's last log lines (LogLine dicts, oldest first) for the event that records it.
copy_crashed = Signal()


def crash_lines(robot_id: str, skill_id: str, component_id: str) -> list[dict[str, Any]]:
    """Return a crashed cloud copy's last log lines, as the receivers of copy_crashed answer them."""
    for _, answer in copy_crashed.send_robust(None, robot_id=robot_id, skill=skill_id, component=component_id):
        if isinstance(answer, list):
            return answer
        if isinstance(answer, Exception):
            logger.warning("the last lines of %s/%s/%s: %r", robot_id, skill_id, component_id, answer)
    return []


# --------------------------------------------------------------------------- recording outcomes


def set_status(instance: CloudInstance, status: str, message: str = "") -> None:
    """Record the copy's status, and the component's when the copy is the active instance."""
    robot_id, skill_id, component_id = who(instance)
    with transaction.atomic():
        if not hold_robot(robot_id):
            return  # its robot was deleted meanwhile, with the copy's rows
        CloudInstance.objects.filter(pk=instance.pk).update(status=status, message=message, updated_at=timezone.now())
        instance.status, instance.message = status, message
        component = Component.objects.select_for_update().filter(pk=instance.component_id).first()
        if component is not None and cloud_is_active(component):
            component.status, component.message = status, message
            component.save(update_fields=["status", "message", "updated_at"])
            data = {"skill": skill_id, "component": component_id, "status": status, "location": "cloud"}
            announce(robot_id, Event.COMPONENT_STATUS, {**data, "message": message} if message else data)


def cloud_is_active(component: Component) -> bool:
    """Tell whether the cloud copy is the component's active instance (not a migration's target)."""
    return component.active_location == Location.CLOUD and component.status != CS.MIGRATING


def record_running(instance: CloudInstance, endpoint: dict[str, Any]) -> bool:
    """Record that the copy runs, unless it is no longer wanted; return whether it was recorded.

    A stop (or `cloud_down`) may land while the copy starts: then the caller removes what it started,
    or the copy would outlive the cloud that no longer wants it.
    """
    robot_id, skill_id, component_id = who(instance)
    with transaction.atomic():
        if not hold_robot(robot_id):
            return True  # its robot was deleted meanwhile, with the copy's rows: the reconciler removes orphans
        wanted = CloudInstance.objects.filter(pk=instance.pk, desired=RUNNING).update(
            status=CS.RUNNING, container=endpoint, message="", restart_at=None, updated_at=timezone.now()
        )
        if not wanted:
            return False
        instance.status, instance.container = CS.RUNNING, endpoint
        component = Component.objects.select_for_update().filter(pk=instance.component_id).first()
        if component is None:
            return True
        component.container = {**component.container, "cloud": endpoint}
        fields = ["container", "updated_at"]
        active = cloud_is_active(component)
        if active:
            component.status = CS.RUNNING
            component.message = ""
            fields += ["status", "message"]
        component.save(update_fields=fields)
        record_event(
            f"Cloud copy of {component_id} runs ({endpoint.get('runtime')} {str(endpoint.get('id', ''))[:12]})",
            robot_id=robot_id,
            kind="cloud_component_running",
            skill=skill_id,
            component=component_id,
            data={"container": endpoint},
        )
        status = {"skill": skill_id, "component": component_id, "status": CS.RUNNING.value, "location": "cloud"}
        if active:
            announce(robot_id, Event.COMPONENT_STATUS, status)
        announce(robot_id, Event.COMPONENT_INFORMATION, info_data(skill_id, component_id, endpoint))
        tell_robot(robot_id, Event.COMPONENT_STATUS, status)
        tell_robot(robot_id, Event.COMPONENT_INFORMATION, info_data(skill_id, component_id, endpoint))
    return True


def fail(instance: CloudInstance, reason: str, *, logs: list[str] | None = None) -> None:
    """Remove whatever runs of the copy, record why it failed, and tell the robot."""
    robot_id, skill_id, component_id = who(instance)
    if logs is None:
        logs = []
        try:
            logs = with_runtime(robot_id, lambda runtime: runtime.logs(skill_id, component_id, LOG_TAIL))
        except RuntimeFailure:
            pass
    lines = crash_lines(robot_id, skill_id, component_id)  # before the stop removes a container and its log
    try:
        with_runtime(robot_id, lambda runtime: runtime.stop(skill_id, component_id))
    except RuntimeFailure as exc:
        logger.warning("could not remove the failed cloud copy of %s/%s/%s: %s", robot_id, skill_id, component_id, exc)
    reason = reason[:1800]
    with transaction.atomic():
        if not hold_robot(robot_id):
            return  # its robot was deleted meanwhile, with the copy's rows
        CloudInstance.objects.filter(pk=instance.pk).update(
            status=CS.FAILED, desired=STOPPED, message=reason, container={}, restart_at=None, updated_at=timezone.now()
        )
        component = Component.objects.select_for_update().filter(pk=instance.component_id).first()
        if component is None:
            return
        if cloud_is_active(component):
            component.status = CS.FAILED
            component.message = f"its cloud copy failed: {reason}"
            component.save(update_fields=["status", "message", "updated_at"])
        record_event(
            f"Cloud copy of {component_id} failed: {reason}",
            robot_id=robot_id,
            level=Level.ERROR,
            kind="cloud_component_failed",
            skill=skill_id,
            component=component_id,
            data={"logs": logs[-LOG_TAIL:], "lines": lines},
        )
        status = {
            "skill": skill_id,
            "component": component_id,
            "status": CS.FAILED.value,
            "location": "cloud",
            "message": reason,
        }
        if cloud_is_active(component):
            announce(robot_id, Event.COMPONENT_STATUS, status)
        tell_robot(robot_id, Event.COMPONENT_STATUS, status)


def info_data(skill_id: str, component_id: str, endpoint: dict[str, Any]) -> dict[str, Any]:
    return {"skill": skill_id, "component": component_id, "location": "cloud", "container": endpoint}


def announce(robot_id: str, event: Event, data: dict[str, Any]) -> None:
    publish_on_commit(robot_id, client_frame(event, {"robot": robot_id, **data}))


def tell_robot(robot_id: str, event: Event, data: dict[str, Any]) -> None:
    transaction.on_commit(lambda: push_to_robot(robot_id, event, data), robust=True)


def cloud_reports(robot_id: str) -> list[tuple[Event, dict[str, Any]]]:
    """Return what a (re)connecting robot should hear about its cloud copies that run or failed."""
    return cloud_reports_for([robot_id])[robot_id]


def cloud_reports_for(robot_ids: list[str]) -> dict[str, list[tuple[Event, dict[str, Any]]]]:
    """Return ``cloud_reports`` of many robots in one query (robots connecting at once)."""
    reports: dict[str, list[tuple[Event, dict[str, Any]]]] = {robot_id: [] for robot_id in robot_ids}
    for instance in CloudInstance.objects.select_related("component__skill").filter(
        component__skill__robot_id__in=robot_ids, status__in=(CS.RUNNING, CS.FAILED)
    ):
        skill_id, component_id = instance.component.skill.skill_id, instance.component.component_id
        status: dict[str, Any] = {
            "skill": skill_id,
            "component": component_id,
            "status": instance.status,
            "location": "cloud",
        }
        if instance.status == CS.FAILED and instance.message:
            status["message"] = instance.message[:1800]
        robot_reports = reports[instance.component.skill.robot_id]
        robot_reports.append((Event.COMPONENT_STATUS, status))
        if instance.status == CS.RUNNING and instance.container:
            robot_reports.append((Event.COMPONENT_INFORMATION, info_data(skill_id, component_id, instance.container)))
    return reports
