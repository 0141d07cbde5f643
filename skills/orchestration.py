"""Cloud orchestration (thesis §3.2): run the cloud copies of components and a ROS master per robot.

The database holds what should run (`CloudInstance.desired`, set by the robot's requests);
Celery tasks make the engine match it for one component at a time (`converge`), and the
reconciler (`reconcile`, on the beat schedule) compares everything that runs with it:
it restarts crashed copies with backoff, relaunches missing ones, removes orphans and
turns container stats into metrics. Robots hear of their cloud copies through
`component_status` and `component_information` (with the address and published ports).

Every step on a component runs under that component's orchestration lock, so two workers
never act on one component at once; each request carries a fresh launch token, so a task
that was overtaken by a newer request (start, stop, start in quick succession) does nothing.
The engine's objects carry labels (see `cloudruntime`), so a step repeated after a worker
died finds what the first attempt created instead of creating it twice.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import ipaddress
import logging
import secrets
import socket
import time
from collections.abc import Awaitable, Callable
from datetime import timedelta
from typing import Any, TypeVar

from django.conf import settings
from django.db import transaction
from django.utils import timezone

from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import Event, Location, MetricPoint
from bridgeos_agent.rosnames import instance_namespace
from bridgeos_agent.runtime.base import ComponentState, RuntimeFailure, Status
from bridgeos_agent.skillconfig import parse_skill_config
from monitoring import prometheus
from monitoring.choices import Level
from monitoring.live import publish_on_commit
from monitoring.services import record_event
from robots.models import Robot
from robots.services import client_frame, push_to_robot

from .cloudruntime import (
    KIND_COMPONENT,
    KIND_ROS_MASTER,
    NO_RESTARTS,
    CloudRuntime,
    CloudSpec,
    EngineBusy,
    Observed,
    create_cloud_runtime,
    object_name,
    ros_networking,
    runtime_name,
)
from .locks import LockBusy, orchestration_lock
from .models import CloudInstance, Component, RobotCloud

__all__ = [
    "TryAgain",
    "converge",
    "converge_ros_master",
    "give_up",
    "reconcile",
    "request_start",
    "request_stop",
    "ros_master_for",
]

logger = logging.getLogger(__name__)
T = TypeVar("T")

RUNNING, STOPPED = CloudInstance.Desired.RUNNING, CloudInstance.Desired.STOPPED
LOG_TAIL = 20


class TryAgain(Exception):
    """A step could not be done now (engine unreachable, lock busy); a retry may succeed."""


class LaunchFailed(Exception):
    """A copy cannot run as configured; retrying will not help."""


# --------------------------------------------------------------------------- running the runtime


def with_runtime(robot_id: str, operation: Callable[[CloudRuntime], Awaitable[T]], *, name: str | None = None) -> T:
    """Run an async operation on a fresh cloud runtime for a robot, from synchronous code."""

    async def main() -> T:
        runtime = create_cloud_runtime(robot_id, name)
        try:
            return await operation(runtime)
        finally:
            await runtime.close()

    try:
        asyncio.get_running_loop()
    except RuntimeError:
        return asyncio.run(main())
    # Called from inside an event loop (a test, an eager task): run on a thread of its own.
    with concurrent.futures.ThreadPoolExecutor(1) as pool:
        return pool.submit(asyncio.run, main()).result()


# --------------------------------------------------------------------------- requests (in the caller's transaction)


def request_start(component: Component) -> CloudInstance:
    """Want the component's cloud copy running; a task makes it so once this transaction commits."""
    instance, _ = CloudInstance.objects.select_for_update().get_or_create(component=component)
    instance.desired = RUNNING
    instance.token = secrets.token_hex(8)
    instance.status = CS.PENDING
    instance.runtime = runtime_name()
    instance.message = ""
    instance.restarts = 0
    instance.crashes = []
    instance.restart_at = None
    instance.save()
    _enqueue_on_commit("start_cloud_component", instance.pk, instance.token)
    return instance


def running_copy(token: str) -> tuple[str, str, str] | None:
    """Return (robot, skill, component) of the cloud copy a launch token names, while it is wanted running."""
    if not token:
        return None
    found = (
        CloudInstance.objects.filter(token=token, desired=RUNNING)
        .values_list("component__skill__robot_id", "component__skill__skill_id", "component__component_id")
        .first()
    )
    return tuple(found) if found else None


def request_stop(component: Component) -> CloudInstance:
    """Want the component's cloud copy gone; a task removes it once this transaction commits."""
    instance, _ = CloudInstance.objects.select_for_update().get_or_create(component=component)
    instance.desired = STOPPED
    instance.token = secrets.token_hex(8)
    if instance.status != CS.STOPPED:
        instance.status = CS.STOPPING
    instance.restart_at = None
    instance.save()
    _enqueue_on_commit("stop_cloud_component", instance.pk, instance.token)
    return instance


def _enqueue_on_commit(task_name: str, *args: Any) -> None:
    from . import tasks

    task = getattr(tasks, task_name)
    transaction.on_commit(lambda: task.delay(*args), robust=True)


# --------------------------------------------------------------------------- one component


def converge(instance_id: int, token: str | None = None) -> str:
    """Make one component's cloud copy what its row wants; return what was done."""
    try:
        with orchestration_lock(f"instance:{instance_id}"):
            instance = _instance(instance_id)
            if instance is None:
                return "gone"
            if token is not None and instance.token != token:
                return "superseded"
            if instance.desired == RUNNING:
                return _run(instance)
            return _stop(instance)
    except LockBusy as exc:
        raise TryAgain(str(exc)) from None


def give_up(instance_id: int, token: str, reason: str) -> None:
    """Roll a start back for good: remove what runs, mark it failed, tell the robot why."""
    with orchestration_lock(f"instance:{instance_id}"):
        instance = _instance(instance_id)
        if instance is None or instance.token != token:
            return
        _fail(instance, reason)


def _instance(instance_id: int) -> CloudInstance | None:
    return (
        CloudInstance.objects.select_related("component__skill__robot", "component__skill")
        .filter(pk=instance_id)
        .first()
    )


def _who(instance: CloudInstance) -> tuple[str, str, str]:
    component = instance.component
    return component.skill.robot_id, component.skill.skill_id, component.component_id


def _run(instance: CloudInstance) -> str:
    """Start the copy (or adopt the one that runs), wait until it runs, and report it."""
    robot_id, skill_id, component_id = _who(instance)
    try:
        spec = cloud_spec(instance)
        subnet = cloud_subnet(instance.component.skill.robot)
    except LaunchFailed as exc:
        _fail(instance, str(exc))
        return "failed"
    if instance.status not in (CS.STARTING, CS.RUNNING):
        _set_status(instance, CS.STARTING)
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
        if _unreachable(exc) or isinstance(exc, EngineBusy):
            raise TryAgain(str(exc)) from None
        _fail(instance, str(exc))
        return "failed"
    if state.status is not Status.RUNNING:
        reason = state.message or f"it ended at once (exit code {state.exit_code})"
        _fail(instance, f"component {component_id} did not start in the cloud: {reason}", logs=logs)
        return "failed"
    _record_running(instance, endpoint)
    return "running"


def _stop(instance: CloudInstance) -> str:
    """Remove the copy and record that it is stopped."""
    robot_id, skill_id, component_id = _who(instance)
    try:
        with_runtime(robot_id, lambda runtime: runtime.stop(skill_id, component_id))
    except RuntimeFailure as exc:
        raise TryAgain(str(exc)) from None
    with transaction.atomic():
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
        _announce(robot_id, Event.COMPONENT_INFORMATION, _info_data(skill_id, component_id, {}))
    return "stopped"


def cloud_spec(instance: CloudInstance) -> CloudSpec:
    """Build the cloud launch of a component: its cloud launch spec, limits, volumes and the env contract."""
    component = instance.component
    skill = component.skill
    robot = skill.robot
    config = parse_skill_config(skill.config)
    declared = config.components.get(component.component_id)
    if declared is None:
        raise LaunchFailed(f"skill {skill.skill_id} has no component {component.component_id} any more")
    if declared.cloud is None:
        raise LaunchFailed(
            f"component {component.component_id} has no cloud launch spec (components.{component.component_id}.cloud)"
        )
    env = {
        "BRIDGEOS_ROBOT": robot.id,
        "BRIDGEOS_SKILL": skill.skill_id,
        "BRIDGEOS_COMPONENT": component.component_id,
        "BRIDGEOS_LOCATION": Location.CLOUD.value,
    }
    master = robot.ros_master or settings.BRIDGEOS["CLOUD_ROS_MASTER"]
    if master:
        env["ROS_MASTER_URI"] = master
    # The Skill's manager runs on the robot: the cloud relays this copy's calls to it (skills.api.manager).
    env["BRIDGEOS_MANAGER_URL"] = f"{settings.BRIDGEOS['CLOUD_URL'].rstrip('/')}/api/cloud/manager/{instance.token}"
    if declared.ros:
        env["ROS_NAMESPACE"] = instance_namespace(skill.skill_id, component.component_id, "cloud")
        env.update(_ros_address(robot.id, skill.skill_id, component.component_id))
    return CloudSpec(
        robot=robot.id,
        skill=skill.skill_id,
        component=component.component_id,
        location=Location.CLOUD.value,
        launch=declared.cloud,
        resources=declared.resources,
        env=env,
        volumes=tuple(config.volumes),
        restart=NO_RESTARTS,
        ros=declared.ros,
        token=instance.token,
    )


def cloud_subnet(robot: Robot) -> str | None:
    """Return the robot's cloud subnet (IPAM), which its cloud network is created with."""
    from django.core.exceptions import ValidationError

    from network.ipam import subnets

    try:
        return subnets(robot)[1]
    except ValidationError as exc:
        raise LaunchFailed(f"robot {robot.id} has no cloud subnet: {'; '.join(exc.messages)}") from None


def _ros_address(robot_id: str, skill_id: str, component_id: str) -> dict[str, str]:
    """Say how TCPROS peers reach a cloud ROS node: the cloud host's address, or its name on the overlay."""
    if runtime_name() != "process" and ros_networking() == "overlay":
        return {"ROS_HOSTNAME": object_name(robot_id, skill_id, component_id)}
    host = settings.BRIDGEOS["CLOUD_HOST"]
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return {"ROS_HOSTNAME": host}
    return {"ROS_IP": host}


def _unreachable(exc: RuntimeFailure) -> bool:
    text = str(exc)
    return "cannot reach" in text or "Connection aborted" in text


# --------------------------------------------------------------------------- recording outcomes


def _set_status(instance: CloudInstance, status: str, message: str = "") -> None:
    """Record the copy's status, and the component's when the copy is the active instance."""
    robot_id, skill_id, component_id = _who(instance)
    with transaction.atomic():
        CloudInstance.objects.filter(pk=instance.pk).update(status=status, message=message, updated_at=timezone.now())
        instance.status, instance.message = status, message
        component = Component.objects.select_for_update().filter(pk=instance.component_id).first()
        if component is not None and _cloud_is_active(component):
            component.status = status
            component.save(update_fields=["status", "updated_at"])
            _announce(
                robot_id,
                Event.COMPONENT_STATUS,
                {"skill": skill_id, "component": component_id, "status": status, "location": "cloud"},
            )


def _cloud_is_active(component: Component) -> bool:
    """Tell whether the cloud copy is the component's active instance (not a migration's target)."""
    return component.active_location == Location.CLOUD and component.status != CS.MIGRATING


def _record_running(instance: CloudInstance, endpoint: dict[str, Any]) -> None:
    robot_id, skill_id, component_id = _who(instance)
    with transaction.atomic():
        CloudInstance.objects.filter(pk=instance.pk).update(
            status=CS.RUNNING, container=endpoint, message="", restart_at=None, updated_at=timezone.now()
        )
        instance.status, instance.container = CS.RUNNING, endpoint
        component = Component.objects.select_for_update().filter(pk=instance.component_id).first()
        if component is None:
            return
        component.container = {**component.container, "cloud": endpoint}
        fields = ["container", "updated_at"]
        active = _cloud_is_active(component)
        if active:
            component.status = CS.RUNNING
            fields.append("status")
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
            _announce(robot_id, Event.COMPONENT_STATUS, status)
        _announce(robot_id, Event.COMPONENT_INFORMATION, _info_data(skill_id, component_id, endpoint))
        _tell_robot(robot_id, Event.COMPONENT_STATUS, status)
        _tell_robot(robot_id, Event.COMPONENT_INFORMATION, _info_data(skill_id, component_id, endpoint))


def _fail(instance: CloudInstance, reason: str, *, logs: list[str] | None = None) -> None:
    """Remove whatever runs of the copy, record why it failed, and tell the robot."""
    robot_id, skill_id, component_id = _who(instance)
    if logs is None:
        logs = []
        try:
            logs = with_runtime(robot_id, lambda runtime: runtime.logs(skill_id, component_id, LOG_TAIL))
        except RuntimeFailure:
            pass
    try:
        with_runtime(robot_id, lambda runtime: runtime.stop(skill_id, component_id))
    except RuntimeFailure as exc:
        logger.warning("could not remove the failed cloud copy of %s/%s/%s: %s", robot_id, skill_id, component_id, exc)
    reason = reason[:1800]
    with transaction.atomic():
        CloudInstance.objects.filter(pk=instance.pk).update(
            status=CS.FAILED, desired=STOPPED, message=reason, container={}, restart_at=None, updated_at=timezone.now()
        )
        component = Component.objects.select_for_update().filter(pk=instance.component_id).first()
        if component is None:
            return
        if _cloud_is_active(component):
            component.status = CS.FAILED
            component.save(update_fields=["status", "updated_at"])
        record_event(
            f"Cloud copy of {component_id} failed: {reason}",
            robot_id=robot_id,
            level=Level.ERROR,
            kind="cloud_component_failed",
            skill=skill_id,
            component=component_id,
            data={"logs": logs[-LOG_TAIL:]},
        )
        status = {
            "skill": skill_id,
            "component": component_id,
            "status": CS.FAILED.value,
            "location": "cloud",
            "message": reason,
        }
        if _cloud_is_active(component):
            _announce(robot_id, Event.COMPONENT_STATUS, status)
        _tell_robot(robot_id, Event.COMPONENT_STATUS, status)


def _info_data(skill_id: str, component_id: str, endpoint: dict[str, Any]) -> dict[str, Any]:
    return {"skill": skill_id, "component": component_id, "location": "cloud", "container": endpoint}


def _announce(robot_id: str, event: Event, data: dict[str, Any]) -> None:
    publish_on_commit(robot_id, client_frame(event, {"robot": robot_id, **data}))


def _tell_robot(robot_id: str, event: Event, data: dict[str, Any]) -> None:
    transaction.on_commit(lambda: push_to_robot(robot_id, event, data), robust=True)


def cloud_reports(robot_id: str) -> list[tuple[Event, dict[str, Any]]]:
    """Return what a (re)connecting robot should hear about its cloud copies that run or failed."""
    reports: list[tuple[Event, dict[str, Any]]] = []
    for instance in CloudInstance.objects.select_related("component__skill").filter(
        component__skill__robot_id=robot_id, status__in=(CS.RUNNING, CS.FAILED)
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
        reports.append((Event.COMPONENT_STATUS, status))
        if instance.status == CS.RUNNING and instance.container:
            reports.append((Event.COMPONENT_INFORMATION, _info_data(skill_id, component_id, instance.container)))
    return reports


# --------------------------------------------------------------------------- ROS masters


def dedicated_masters() -> bool:
    """Tell whether robots without a ROS master get one of their own in the cloud."""
    configured = settings.BRIDGEOS["CLOUD_ROS_MASTERS"]
    if configured:
        return configured.strip().lower() in ("1", "true", "yes", "on")
    return runtime_name() in ("swarm", "docker")


def ros_master_for(robot_id: str, reported: str | None) -> str:
    """Return the ROS master a connecting robot's components use (in the caller's transaction).

    Its own when it reported one; else the cloud's shared one (BRIDGEOS_CLOUD_ROS_MASTER);
    else, with dedicated masters, one of its own in the cloud, started once this commits.
    """
    if reported:
        return reported
    shared = settings.BRIDGEOS["CLOUD_ROS_MASTER"]
    if shared or not dedicated_masters():
        return shared or ""
    cloud, _ = RobotCloud.objects.select_for_update().get_or_create(robot_id=robot_id)
    if cloud.ros_master_port is None:
        cloud.ros_master_port = _free_master_port()
        cloud.ros_master_status = CS.PENDING
        cloud.save(update_fields=["ros_master_port", "ros_master_status", "updated_at"])
    _enqueue_on_commit("ensure_ros_master", robot_id)
    return master_url(cloud.ros_master_port)


def master_url(port: int) -> str:
    """Return the URL of a dedicated ROS master on the cloud host."""
    return f"http://{settings.BRIDGEOS['CLOUD_HOST']}:{port}"


def _free_master_port() -> int:
    """Pick the lowest port of the configured range no other robot holds and nothing listens on."""
    low, _, high = settings.BRIDGEOS["CLOUD_ROS_MASTER_PORTS"].partition("-")
    taken = set(RobotCloud.objects.exclude(ros_master_port=None).values_list("ros_master_port", flat=True))
    for port in range(int(low), int(high or low) + 1):
        if port in taken:
            continue
        with socket.socket() as probe:
            try:
                probe.bind(("0.0.0.0", port))
            except OSError:
                continue
        return port
    raise LaunchFailed(f"no free port for a ROS master in BRIDGEOS_CLOUD_ROS_MASTER_PORTS={low}-{high}")


def converge_ros_master(robot_id: str) -> str:
    """Run the robot's dedicated ROS master while it uses it; stop it once it uses another."""
    try:
        with orchestration_lock(f"master:{robot_id}"):
            cloud = RobotCloud.objects.select_related("robot").filter(robot_id=robot_id).first()
            if cloud is None or cloud.ros_master_port is None:
                return "none"
            wanted = cloud.robot.ros_master == master_url(cloud.ros_master_port)
            try:
                if not wanted:
                    with_runtime(robot_id, lambda runtime: runtime.stop_ros_master())
                    _set_master(cloud, CS.STOPPED)
                    return "stopped"
                state = with_runtime(robot_id, lambda runtime: runtime.start_ros_master(cloud.ros_master_port))
            except RuntimeFailure as exc:
                if _unreachable(exc):
                    raise TryAgain(str(exc)) from None
                _set_master(cloud, CS.FAILED, str(exc))
                return "failed"
            if state.status is Status.RUNNING and _answers(cloud.ros_master_port, timeout=15.0):
                _set_master(cloud, CS.RUNNING)
                return "running"
            if state.status is Status.RUNNING:
                raise TryAgain(f"the ROS master of {robot_id} runs but does not answer on {cloud.ros_master_port} yet")
            _set_master(cloud, CS.FAILED, state.message or f"exit code {state.exit_code}")
            return "failed"
    except LockBusy as exc:
        raise TryAgain(str(exc)) from None


def _answers(port: int, *, timeout: float) -> bool:
    """Tell whether something accepts connections on the cloud host's port within ``timeout``."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            socket.create_connection((settings.BRIDGEOS["CLOUD_HOST"], port), timeout=1).close()
            return True
        except OSError:
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.05)


def _set_master(cloud: RobotCloud, status: str, message: str = "") -> None:
    if cloud.ros_master_status == status and cloud.message == message:
        return
    with transaction.atomic():
        RobotCloud.objects.filter(pk=cloud.pk).update(
            ros_master_status=status, message=message, updated_at=timezone.now()
        )
        cloud.ros_master_status, cloud.message = status, message
        text = f"ROS master of robot {cloud.robot_id} on port {cloud.ros_master_port} is {status}"
        record_event(
            text + (f": {message}" if message else ""),
            robot_id=cloud.robot_id,
            level=Level.ERROR if status == CS.FAILED else Level.INFO,
            kind="cloud_ros_master",
            data={"port": cloud.ros_master_port, "status": status},
        )


# --------------------------------------------------------------------------- the reconciler


def reconcile(*, now: float | None = None) -> dict[str, int]:
    """Compare what should run with what runs and fix the difference; return what was done."""
    try:
        # One round at a time: a slow round must not be doubled by the next beat.
        with orchestration_lock("reconcile", wait=0):
            return _reconcile(time.time() if now is None else now)
    except LockBusy:
        return {"skipped": 1}


def _reconcile(now: float) -> dict[str, int]:
    done = {"restarted": 0, "crashed": 0, "removed": 0, "relaunched": 0, "masters": 0, "metrics": 0}
    observed = with_runtime("reconciler", lambda runtime: runtime.observe())
    by_key: dict[tuple[str, str, str], Observed] = {}
    masters: dict[str, Observed] = {}
    for item in observed:
        if item.kind == KIND_ROS_MASTER:
            masters[item.robot] = item
        elif item.kind == KIND_COMPONENT:
            by_key[item.key] = item
    instances = list(
        CloudInstance.objects.select_related("component__skill").exclude(desired=STOPPED, status=CS.STOPPED)
    )
    wanted: set[tuple[str, str, str]] = set()
    for instance in instances:
        robot_id, skill_id, component_id = _who(instance)
        key = (robot_id, skill_id, component_id)
        if instance.desired == RUNNING:
            wanted.add(key)
        try:
            with orchestration_lock(f"instance:{instance.pk}", wait=0):
                fresh = _instance(instance.pk)
                if fresh is not None:
                    outcome = _reconcile_instance(fresh, by_key.get(key), now)
                    if outcome:
                        done[outcome] += 1
        except LockBusy:
            logger.info("reconcile %s/%s/%s: a task is working on it", robot_id, skill_id, component_id)
            continue
        except (TryAgain, RuntimeFailure) as exc:
            logger.warning("reconcile %s/%s/%s: %s", robot_id, skill_id, component_id, exc)
        except Exception:
            # One copy the reconciler cannot handle must not keep it from the others.
            logger.exception("reconcile %s/%s/%s failed", robot_id, skill_id, component_id)
    for key, item in by_key.items():
        if key not in wanted:
            done["removed"] += _remove_orphan(item)
    done["masters"] = _reconcile_masters(masters)
    _remove_orphan_networks()
    done["metrics"] = collect_stats({key[0] for key in wanted})
    prometheus.reconciled(done)
    return done


def _reconcile_instance(instance: CloudInstance, seen: Observed | None, now: float) -> str | None:
    """Bring one copy in line with its row; return what was done, if anything."""
    robot_id = instance.component.skill.robot_id
    if instance.desired == STOPPED:
        if seen is not None or instance.status not in (CS.STOPPED, CS.FAILED):
            _stop(instance)
            return "removed" if seen is not None else None
        return None
    if instance.status == CS.FAILED:
        return None  # given up on: a new start request tries again
    running = seen is not None and seen.status is Status.RUNNING
    if running:
        if instance.status != CS.RUNNING:
            endpoint = with_runtime(robot_id, lambda runtime: runtime.endpoint(cloud_spec(instance)))
            _record_running(instance, endpoint)
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
            _run(instance)
            return "relaunched"
    return None


def _on_crash(instance: CloudInstance, seen: Observed | None, now: float) -> str:
    """Log a crash with the copy's last output and schedule its restart, or give up after too many."""
    robot_id, skill_id, component_id = _who(instance)
    logs = with_runtime(robot_id, lambda runtime: runtime.logs(skill_id, component_id, LOG_TAIL))
    window = settings.BRIDGEOS["CLOUD_RESTART_WINDOW_S"]
    crashes = [t for t in instance.crashes if now - t <= window] + [now]
    code = seen.exit_code if seen is not None else None
    why = "its process is gone" if seen is None else (seen.message or f"exit code {code}")
    if len(crashes) > settings.BRIDGEOS["CLOUD_MAX_RESTARTS"]:
        reason = f"crashed {len(crashes)} times within {window:g} s (last: {why}); not restarted again"
        _fail(instance, reason, logs=logs)
        return "crashed"
    delay = min(2.0 ** (len(crashes) - 1), settings.BRIDGEOS["CLOUD_RESTART_BACKOFF_MAX_S"])
    with transaction.atomic():
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
        if _cloud_is_active(component):
            component.status = CS.STARTING
            component.save(update_fields=["status", "updated_at"])
            _announce(robot_id, Event.COMPONENT_STATUS, status)
        record_event(
            f"Cloud copy of {component_id} crashed ({why}); restarting in {delay:g} s",
            robot_id=robot_id,
            level=Level.ERROR,
            kind="cloud_component_crashed",
            skill=skill_id,
            component=component_id,
            data={"exit_code": code, "logs": logs[-LOG_TAIL:], "restart": len(crashes), "delay_s": delay},
        )
        _tell_robot(robot_id, Event.COMPONENT_STATUS, status)
    return "crashed"


def _restart(instance: CloudInstance) -> str:
    """Start a crashed copy again and record the outcome."""
    robot_id, skill_id, component_id = _who(instance)
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
        _record_running(instance, endpoint)
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


def _remove_orphan_networks() -> None:
    """Remove the cloud networks of robots that no longer exist."""
    networks = with_runtime("reconciler", lambda runtime: runtime.networks())
    gone = set(networks) - set(Robot.objects.filter(id__in=list(networks)).values_list("id", flat=True))
    for robot_id in gone:
        name = networks[robot_id]
        with_runtime("reconciler", lambda runtime, name=name: runtime.remove_network_named(name))


# --------------------------------------------------------------------------- stats


def collect_stats(robot_ids: set[str]) -> int:
    """Measure the running cloud copies of these robots; store, broadcast and send the figures."""
    if not robot_ids:
        return 0
    from monitoring.ingest import MetricWriter
    from monitoring.live import LiveFeed

    async def measure_all() -> dict[str, list[MetricPoint]]:
        async def one(robot_id: str) -> tuple[str, list[MetricPoint]]:
            runtime = create_cloud_runtime(robot_id)
            try:
                usages = await runtime.stats()
            except RuntimeFailure:
                return robot_id, []
            finally:
                await runtime.close()
            ts = time.time()
            labels = {"location": "cloud"}
            points = []
            for (skill_id, component_id), usage in usages.items():
                for name, value in (("cpu", round(100 * usage.cpu, 2)), ("ram", round(usage.ram, 1))):
                    point = MetricPoint(
                        name=name, value=float(value), ts=ts, skill=skill_id, component=component_id, labels=labels
                    )
                    points.append(point)
            return robot_id, points

        measured = dict(await asyncio.gather(*(one(robot_id) for robot_id in sorted(robot_ids))))
        measured = {robot_id: points for robot_id, points in measured.items() if points}
        if measured:
            # The ingest the robots' metrics go through: COPY in one batch, then the live feed.
            writer = MetricWriter()
            writer.start()
            feed = LiveFeed()
            for robot_id, points in measured.items():
                writer.add(robot_id, points)
                feed.add_metrics(robot_id, points)
            await writer.close()
            await feed.close()
        return measured

    try:
        asyncio.get_running_loop()
        running = True
    except RuntimeError:
        running = False
    if running:
        with concurrent.futures.ThreadPoolExecutor(1) as pool:
            measured = pool.submit(asyncio.run, measure_all()).result()
    else:
        measured = asyncio.run(measure_all())
    for robot_id, points in measured.items():
        push_to_robot(robot_id, Event.METRICS, {"metrics": [p.model_dump(exclude_none=True) for p in points]})
    return sum(len(points) for points in measured.values())
