"""Requests for cloud copies, their launch spec, and running a cloud runtime from synchronous code."""

from __future__ import annotations

import asyncio
import concurrent.futures
import ipaddress
import logging
import os
import secrets
import sys
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

from django.conf import settings
from django.core.exceptions import ValidationError
from django.db import transaction

from bridgeos_agent.imagerefs import split_reference
from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import Location
from bridgeos_agent.ros2graph import DEFAULT_RMW, namespace_arguments
from bridgeos_agent.rosnames import instance_namespace
from bridgeos_agent.runtime.base import RuntimeFailure
from bridgeos_agent.skillconfig import LaunchSpec, parse_skill_config
from bridgeos_cloud.celery import app as celery_app
from network.ipam import subnets
from robots.models import Robot

from ..models import CloudInstance, Component, RobotCloud
from .backends import create_cloud_runtime
from .runtime import (
    NO_RESTARTS,
    CloudRuntime,
    CloudSpec,
    discovery_address,
    object_name,
    ros_networking,
    runtime_name,
)
from .swarmauth import PullRefused, registry_auth

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
    enqueue_on_commit("start_cloud_component", instance.pk, instance.token)
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
    enqueue_on_commit("stop_cloud_component", instance.pk, instance.token)
    return instance


def enqueue_on_commit(task_name: str, *args: Any) -> None:
    """Queue one of the orchestration's Celery tasks once the caller's transaction commits."""
    # By name: the tasks are the door onto this package (loaded when the skills app is ready).
    task = celery_app.tasks[f"skills.tasks.{task_name}"]
    transaction.on_commit(lambda: task.delay(*args), robust=True)


# --------------------------------------------------------------------------- one component


def instance_row(instance_id: int) -> CloudInstance | None:
    return (
        CloudInstance.objects.select_related("component__skill__robot", "component__skill")
        .filter(pk=instance_id)
        .first()
    )


def who(instance: CloudInstance) -> tuple[str, str, str]:
    component = instance.component
    return component.skill.robot_id, component.skill.skill_id, component.component_id


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
    launch = declared.cloud
    if declared.ros_version == 2:
        # A ROS 2 node has no master: it joins the robot's cloud graph (its discovery server).
        namespace = instance_namespace(skill.skill_id, component.component_id, "cloud")
        env.update(ros2_env(robot))
        env["ROS_NAMESPACE"] = namespace
        launch = ros2_launch(launch, namespace)
    else:
        master = robot.ros_master or settings.BRIDGEOS["CLOUD_ROS_MASTER"]
        if master:
            env["ROS_MASTER_URI"] = master
    # The Skill's manager runs on the robot: the cloud relays this copy's calls to it (skills.api.componentsapi).
    env["BRIDGEOS_MANAGER_URL"] = f"{settings.BRIDGEOS['CLOUD_URL'].rstrip('/')}/api/cloud/manager/{instance.token}"
    if declared.ros_version == 1:
        env["ROS_NAMESPACE"] = instance_namespace(skill.skill_id, component.component_id, "cloud")
        env.update(_ros_address(robot.id, skill.skill_id, component.component_id))
    return CloudSpec(
        registry_auth=_registry_auth(component.component_id, launch.image or "", robot),
        robot=robot.id,
        skill=skill.skill_id,
        component=component.component_id,
        location=Location.CLOUD.value,
        launch=launch,
        resources=declared.resources,
        env=env,
        volumes=tuple(config.volumes),
        restart=NO_RESTARTS,
        ros=declared.ros,
        token=instance.token,
    )


def _registry_auth(component_id: str, image: str, robot: Robot) -> str:
    """Return the registry auth a copy's image of the cloud's registry needs; LaunchFailed if it cannot run.

    Such an image must be the digest the Skill was pinned to when it was added, so every copy runs
    the same bytes whatever its tag does later (registry/pinning.py).
    """
    registry, _, reference = split_reference(image)
    if registry and registry == settings.BRIDGEOS["REGISTRY_HOST"] and not reference.startswith("sha256:"):
        raise LaunchFailed(
            f"component {component_id}: the cloud image {image!r} is not pinned by digest"
            " (the Skill was stored without being added through the API): add the Skill again"
        )
    try:
        return registry_auth(image, robot)
    except PullRefused as exc:
        raise LaunchFailed(f"component {component_id}: {exc}") from None


def ros2_env(robot: Robot) -> dict[str, str]:
    """Return the env that puts a cloud copy of the robot's ROS 2 component in the robot's cloud graph."""
    graph = robot.ros2 or {}
    env = {"ROS_DOMAIN_ID": str(graph.get("domain_id", 0)), "RMW_IMPLEMENTATION": graph.get("rmw") or DEFAULT_RMW}
    port = RobotCloud.objects.filter(robot_id=robot.id).values_list("ros2_discovery_port", flat=True).first()
    if robot.ros2 is not None and port is not None:
        # Host-networked copies and host processes reach the server where robots do.
        env["ROS_DISCOVERY_SERVER"] = discovery_address(port)
    else:
        # No server (the robot reported no ROS 2 graph): at least keep the copy's discovery on this host.
        env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    if runtime_name() == "process":
        # The cloud's own venv has the ROS 2 wheels: its python3 comes first for the copy's command.
        env["PATH"] = os.pathsep.join([os.path.dirname(sys.executable), os.environ.get("PATH", os.defpath)])
    else:
        # A container has a /dev/shm of its own, yet Fast DDS takes a host-networked peer for one on the
        # same host and sends it data over shared memory, which never arrives (measured): UDP only.
        env["FASTDDS_BUILTIN_TRANSPORTS"] = "UDPv4"
    return env


def ros2_launch(launch: LaunchSpec, namespace: str) -> LaunchSpec:
    """Return a ROS 2 copy's cloud launch: its command pushed into ``namespace``, the ROS 2 image by default."""
    update: dict[str, Any] = {}
    if launch.command:
        update["command"] = [*launch.command, *namespace_arguments(namespace)]
    if not launch.image and runtime_name() != "process":
        update["image"] = settings.BRIDGEOS["CLOUD_ROS2_IMAGE"]
    return launch.model_copy(update=update) if update else launch


def cloud_subnet(robot: Robot) -> str | None:
    """Return the robot's cloud subnet (IPAM), which its cloud network is created with."""
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


def unreachable(exc: RuntimeFailure) -> bool:
    text = str(exc)
    return "cannot reach" in text or "Connection aborted" in text
