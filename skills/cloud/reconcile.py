"""The reconciler: compare everything that runs with what the rows want, and fix the difference."""

from __future__ import annotations

import logging
import time
from datetime import timedelta
from typing import Any

from django.conf import settings
from django.db import transaction
from django.utils import timezone

from bridgeos_agent.logonce import LogOnce
from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import Event
from bridgeos_agent.runtime.base import ComponentState, RuntimeFailure, Status
from monitoring import prometheus
from monitoring.choices import Level
from monitoring.services import record_event
from robots.models import Robot
from robots.services import hold_robot

from ..models import CloudInstance, Component, RobotCloud
from .converge import run_copy, stop_copy
from .discovery import converge_discovery_server
from .discovery import wanted as discovery_wanted
from .locks import LockBusy, orchestration_lock
from .masters import converge_ros_master, master_url
from .orchestration import (
    LOG_TAIL,
    RUNNING,
    STOPPED,
    TryAgain,
    cloud_spec,
    cloud_subnet,
    instance_row,
    who,
    with_runtime,
)
from .relay import reconcile_relays
from .reporting import announce, cloud_is_active, crash_lines, fail, record_running, tell_robot
from .runtime import (
    KIND_COMPONENT,
    KIND_ROS2_DISCOVERY,
    KIND_ROS_MASTER,
    CloudRuntime,
    Observed,
)
from .stats import collect_stats

logger = logging.getLogger(__name__)

# Per copy, across rounds (the beat runs the reconciler every few seconds in the same worker).
_failed_copies: dict[tuple[str, str, str], LogOnce] = {}


def _failures(key: tuple[str, str, str]) -> LogOnce:
    found = _failed_copies.get(key)
    if found is None:
        found = _failed_copies[key] = LogOnce(logger, "reconcile {}/{}/{}".format(*key), traceback=True)
    return found


def reconcile(*, now: float | None = None) -> dict[str, int]:
    """Compare what should run with what runs and fix the difference; return what was done."""
    try:
        # One round at a time: a slow round must not be doubled by the next beat.
        with orchestration_lock("reconcile", wait=0):
            return _reconcile(time.time() if now is None else now)
    except LockBusy:
        return {"skipped": 1}


def _reconcile(now: float) -> dict[str, int]:
    done = {
        "restarted": 0,
        "crashed": 0,
        "removed": 0,
        "relaunched": 0,
        "masters": 0,
        "ros2_discovery": 0,
        "relays": 0,
        "metrics": 0,
    }
    observed = with_runtime("reconciler", lambda runtime: runtime.observe())
    by_key: dict[tuple[str, str, str], Observed] = {}
    masters: dict[str, Observed] = {}
    servers: dict[str, Observed] = {}
    for item in observed:
        if item.kind == KIND_ROS_MASTER:
            masters[item.robot] = item
        elif item.kind == KIND_ROS2_DISCOVERY:
            servers[item.robot] = item
        elif item.kind == KIND_COMPONENT:
            by_key[item.key] = item
    instances = list(
        CloudInstance.objects.select_related("component__skill").exclude(desired=STOPPED, status=CS.STOPPED)
    )
    wanted: set[tuple[str, str, str]] = set()
    for instance in instances:
        robot_id, skill_id, component_id = who(instance)
        key = (robot_id, skill_id, component_id)
        if instance.desired == RUNNING:
            wanted.add(key)
        try:
            with orchestration_lock(f"instance:{instance.pk}", wait=0):
                fresh = instance_row(instance.pk)
                if fresh is not None:
                    outcome = _reconcile_instance(fresh, by_key.get(key), now)
                    if outcome:
                        done[outcome] += 1
        except LockBusy:
            logger.info("reconcile %s/%s/%s: a task is working on it", robot_id, skill_id, component_id)
            continue
        except (TryAgain, RuntimeFailure) as exc:
            logger.warning("reconcile %s/%s/%s: %s", robot_id, skill_id, component_id, exc)
        except Exception as exc:
            # One copy the reconciler cannot handle must not keep it from the others; said once per distinct error.
            _failures(key).failed(exc)
        else:
            _failures(key).worked()
    for key, item in by_key.items():
        if key not in wanted:
            done["removed"] += _remove_orphan(item)
    done["masters"] = _reconcile_masters(masters)
    done["ros2_discovery"] = _reconcile_discovery_servers(servers)
    done["relays"] = reconcile_relays()
    _remove_orphan_networks()
    done["metrics"] = collect_stats({key[0] for key in wanted})
    prometheus.reconciled(done)
    return done


def _reconcile_instance(instance: CloudInstance, seen: Observed | None, now: float) -> str | None:
    """Bring one copy in line with its row; return what was done, if anything."""
    robot_id = instance.component.skill.robot_id
    if instance.desired == STOPPED:
        if seen is not None or instance.status not in (CS.STOPPED, CS.FAILED):
            stop_copy(instance)
            return "removed" if seen is not None else None
        return None
    if instance.status == CS.FAILED:
        return None  # given up on: a new start request tries again
    running = seen is not None and seen.status is Status.RUNNING
    if running:
        if instance.status != CS.RUNNING:
            spec = cloud_spec(instance)  # reads the database: before, not inside, the runtime's event loop
            endpoint = with_runtime(robot_id, lambda runtime: runtime.endpoint(spec))
            if not record_running(instance, endpoint):
                stop_copy(instance)  # stopped meanwhile
                return "removed"
            return "restarted"
        return None
    if instance.status == CS.RUNNING:
        return _on_crash(instance, seen, now)
    if instance.restart_at is not None:
        if instance.restart_at.timestamp() > now:
            return None
        return _restart(instance)
    if instance.status in (CS.PENDING, CS.STARTING, CS.STOPPING):
        # A start whose task never ran or died: after the start timeout, launch it again.
        stale = timezone.now() - instance.updated_at > timedelta(seconds=settings.BRIDGEOS["CLOUD_START_TIMEOUT_S"])
        if stale:
            run_copy(instance)
            return "relaunched"
    return None


def _on_crash(instance: CloudInstance, seen: Observed | None, now: float) -> str:
    """Log a crash with the copy's last output and schedule its restart, or give up after too many."""
    robot_id, skill_id, component_id = who(instance)
    logs = with_runtime(robot_id, lambda runtime: runtime.logs(skill_id, component_id, LOG_TAIL))
    lines = crash_lines(robot_id, skill_id, component_id)
    window = settings.BRIDGEOS["CLOUD_RESTART_WINDOW_S"]
    crashes = [t for t in instance.crashes if now - t <= window] + [now]
    code = seen.exit_code if seen is not None else None
    why = "its process is gone" if seen is None else (seen.message or f"exit code {code}")
    if len(crashes) > settings.BRIDGEOS["CLOUD_MAX_RESTARTS"]:
        reason = f"crashed {len(crashes)} times within {window:g} s (last: {why}); not restarted again"
        fail(instance, reason, logs=logs)
        return "crashed"
    delay = min(2.0 ** (len(crashes) - 1), settings.BRIDGEOS["CLOUD_RESTART_BACKOFF_MAX_S"])
    with transaction.atomic():
        if not hold_robot(robot_id):
            return "crashed"  # its robot was deleted meanwhile, with the copy's rows
        CloudInstance.objects.filter(pk=instance.pk).update(
            status=CS.STARTING,
            crashes=crashes,
            restart_at=timezone.now() + timedelta(seconds=delay),
            message=f"crashed: {why}",
            updated_at=timezone.now(),
        )
        component = Component.objects.select_for_update().filter(pk=instance.component_id).first()
        if component is None:
            return "crashed"
        status = {
            "skill": skill_id,
            "component": component_id,
            "status": CS.STARTING.value,
            "location": "cloud",
            "message": f"crashed ({why}); restart {len(crashes)} in {delay:g} s",
        }
        if cloud_is_active(component):
            component.status, component.message = CS.STARTING, status["message"]
            component.save(update_fields=["status", "message", "updated_at"])
            announce(robot_id, Event.COMPONENT_STATUS, status)
        record_event(
            f"Cloud copy of {component_id} crashed ({why}); restarting in {delay:g} s",
            robot_id=robot_id,
            level=Level.ERROR,
            kind="cloud_component_crashed",
            skill=skill_id,
            component=component_id,
            data={
                "exit_code": code,
                "logs": logs[-LOG_TAIL:],
                "lines": lines,  # its last stored log lines (issue 36), as a robot's crash event carries them
                "restart": len(crashes),
                "delay_s": delay,
            },
        )
        tell_robot(robot_id, Event.COMPONENT_STATUS, status)
    return "crashed"


def _restart(instance: CloudInstance) -> str:
    """Start a crashed copy again and record the outcome."""
    robot_id, skill_id, component_id = who(instance)
    spec = cloud_spec(instance)
    subnet = cloud_subnet(instance.component.skill.robot)
    timeout = settings.BRIDGEOS["CLOUD_START_TIMEOUT_S"]

    async def again(runtime: CloudRuntime) -> tuple[ComponentState, dict[str, Any]]:
        runtime.subnet = subnet
        state = await runtime.restart(spec)
        if state.status is not Status.RUNNING:
            state = await runtime.wait_running(skill_id, component_id, timeout)
        return state, (await runtime.endpoint(spec) if state.status is Status.RUNNING else {})

    state, endpoint = with_runtime(robot_id, again)
    CloudInstance.objects.filter(pk=instance.pk).update(restarts=instance.restarts + 1, restart_at=None)
    if state.status is Status.RUNNING:
        if not record_running(instance, endpoint):
            stop_copy(instance)  # stopped while it restarted (a stop request, cloud_down)
            return "removed"
        return "restarted"
    # It died again at once: the next round sees it gone and counts another crash.
    instance.status = CS.RUNNING
    CloudInstance.objects.filter(pk=instance.pk).update(status=CS.RUNNING)
    return "restarted"


def _remove_orphan(item: Observed) -> int:
    """Remove an object no row wants, unless a task is busy with that component right now."""
    row = CloudInstance.objects.filter(
        component__skill__robot_id=item.robot,
        component__skill__skill_id=item.skill,
        component__component_id=item.component,
    ).first()
    key = f"instance:{row.pk}" if row is not None else f"orphan:{item.robot}/{item.skill}/{item.component}"
    try:
        with orchestration_lock(key, wait=0):
            if row is not None and CloudInstance.objects.filter(pk=row.pk, desired=RUNNING).exists():
                return 0  # wanted again since the round began
            with_runtime("reconciler", lambda runtime: runtime.remove(item))
    except (LockBusy, RuntimeFailure) as exc:
        logger.info("orphan %s not removed now: %s", item.id, exc)
        return 0
    logger.info("removed orphan %s of robot %s", item.id, item.robot)
    robot = Robot.objects.filter(id=item.robot).first()
    record_event(
        f"Removed an orphaned cloud copy of {item.skill}/{item.component} ({item.id})",
        robot_id=robot.id if robot else None,
        level=Level.WARNING,
        kind="cloud_orphan_removed",
        skill=item.skill,
        component=item.component,
    )
    return 1


def _reconcile_masters(masters: dict[str, Observed]) -> int:
    """Start the dedicated masters robots use that are not running; stop those nobody uses."""
    fixed = 0
    clouds = {c.robot_id: c for c in RobotCloud.objects.select_related("robot").exclude(ros_master_port=None)}
    for robot_id, cloud in clouds.items():
        wanted = cloud.robot.ros_master == master_url(cloud.ros_master_port)
        seen = masters.get(robot_id)
        running = seen is not None and seen.status is Status.RUNNING
        if wanted != running:
            try:
                converge_ros_master(robot_id)
                fixed += 1
            except TryAgain as exc:
                logger.info("ROS master of %s: %s", robot_id, exc)
    for robot_id, seen in masters.items():
        if robot_id not in clouds:
            try:
                with_runtime(robot_id, lambda runtime, seen=seen: runtime.remove(seen))
                fixed += 1
            except RuntimeFailure as exc:
                logger.info("orphan ROS master of %s not removed now: %s", robot_id, exc)
    return fixed


def _reconcile_discovery_servers(servers: dict[str, Observed]) -> int:
    """Start the ROS 2 discovery servers robots use that are not running; remove those of robots gone."""
    fixed = 0
    clouds = {c.robot_id: c for c in RobotCloud.objects.select_related("robot").exclude(ros2_discovery_port=None)}
    for robot_id, cloud in clouds.items():
        seen = servers.get(robot_id)
        running = seen is not None and seen.status is Status.RUNNING
        if discovery_wanted(cloud.robot) != running:
            try:
                converge_discovery_server(robot_id)
                fixed += 1
            except TryAgain as exc:
                logger.info("ROS 2 discovery server of %s: %s", robot_id, exc)
    for robot_id, seen in servers.items():
        if robot_id not in clouds:
            try:
                with_runtime(robot_id, lambda runtime, seen=seen: runtime.remove(seen))
                fixed += 1
            except RuntimeFailure as exc:
                logger.info("orphan ROS 2 discovery server of %s not removed now: %s", robot_id, exc)
    return fixed


def _remove_orphan_networks() -> None:
    """Remove the cloud networks of robots that no longer exist."""
    networks = with_runtime("reconciler", lambda runtime: runtime.networks())
    gone = set(networks) - set(Robot.objects.filter(id__in=list(networks)).values_list("id", flat=True))
    for robot_id in gone:
        name = networks[robot_id]
        with_runtime("reconciler", lambda runtime, name=name: runtime.remove_network_named(name))
