"""Docker's documents for the cloud runtimes: a copy's Swarm service request, task states, CPU shares."""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

from docker.types import (
    ContainerSpec,
    EndpointSpec,
    LogConfig,
    Mount,
    NetworkAttachmentConfig,
    Placement,
    Resources,
    RestartPolicy,
    TaskTemplate,
)

from bridgeos_agent.runtime.base import VOLUMES_ENV, ComponentSpec, ComponentState, Status
from bridgeos_agent.runtime.docker import MIN_CPUS, MIN_MEMORY, VOLUMES_MOUNT
from bridgeos_agent.runtime.usage import MIB

from .runtime import LABEL_TOKEN, CloudSpec, labels, volumes_root

STOP_GRACE_NS = 10 * 1_000_000_000

# Task states (docker/api/types/swarm/task.go) and what they mean for a copy.
STARTING = {"new", "allocated", "pending", "assigned", "accepted", "preparing", "ready", "starting"}
FAILED = {"failed", "rejected", "orphaned", "remove"}
DONE = {"complete", "shutdown"}


def log_driver() -> dict[str, Any]:
    config = LogConfig(type=LogConfig.types.JSON, config={"max-size": str(10 * MIB), "max-file": "2"})
    return {"Name": config.type, "Options": config.config}


def task_key(task: Mapping[str, Any]) -> tuple[str, int]:
    """Order a service's tasks: the last created last (then the highest version).

    Not the version first: a replaced task's version moves past its replacement's when Swarm
    marks it for shutdown, while the replacement is still being placed. Docker trims the
    creation time's trailing zeros, so its fraction is padded to compare as text.
    """
    stamp, _, fraction = str(task.get("CreatedAt", "")).removesuffix("Z").partition(".")
    return (f"{stamp}.{fraction:0<9}", int((task.get("Version") or {}).get("Index", 0)))


def task_state(skill: str, component: str, task: Mapping[str, Any]) -> ComponentState:
    """Map a task's state to a component's state."""
    status = task.get("Status") or {}
    state = str(status.get("State", ""))
    container = status.get("ContainerStatus") or {}
    code = container.get("ExitCode")
    message = status.get("Err") or None
    if state == "running":
        mapped = Status.RUNNING
    elif state in STARTING:
        mapped = Status.STARTING
    elif state == "complete":
        mapped = Status.EXITED
    elif state in FAILED or (state in DONE and code not in (None, 0)):
        mapped = Status.FAILED
        message = message or f"task {state} (exit code {code})"
    else:
        mapped = Status.STOPPED
    return ComponentState(
        skill=skill,
        component=component,
        status=mapped,
        pid_or_container_id=(container.get("ContainerID") or task.get("ID")),
        exit_code=code if mapped is not Status.RUNNING else None,
        message=message if mapped is not Status.RUNNING else None,
    )


def service_config(robot: str, name: str, spec: ComponentSpec, network: str | None) -> dict[str, Any]:
    """Build the create-service request of a component's cloud copy."""
    resources = spec.resources
    limits: dict[str, Any] = {}
    if resources.cpu > 0:
        limits["cpu_limit"] = int(min(max(resources.cpu, MIN_CPUS), float(os.cpu_count() or 1)) * 1e9)
    if resources.ram > 0:
        limits["mem_limit"] = max(int(resources.ram * MIB), MIN_MEMORY)
    mounts = [
        Mount(
            target=f"{VOLUMES_MOUNT}/{volume}",
            source=str(volumes_root() / robot / spec.skill / volume),
            type="bind",
        )
        for volume in spec.volumes
    ]
    own_labels = labels(robot, spec.skill, spec.component)
    if isinstance(spec, CloudSpec) and spec.token:
        own_labels[LABEL_TOKEN] = spec.token
    env = {**spec.launch_env(), VOLUMES_ENV: VOLUMES_MOUNT}
    container = ContainerSpec(
        image=spec.launch.image,
        # The launch spec's command replaces the image's CMD, as with docker run.
        args=spec.launch.command,
        env=env,
        labels=own_labels,
        mounts=mounts,
        init=True,
        stop_grace_period=STOP_GRACE_NS,
        hostname=name,
    )
    host = network is None
    template = TaskTemplate(
        container_spec=container,
        resources=Resources(**limits) if limits else None,
        restart_policy=RestartPolicy(condition="none"),
        placement=Placement(constraints=list(spec.launch.placement)) if spec.launch.placement else None,
        networks=[NetworkAttachmentConfig("host" if host else network)],
        log_driver=log_driver(),
    )
    ports = [{"Protocol": "tcp", "TargetPort": port, "PublishMode": "host"} for port in spec.launch.ports if not host]
    return {
        "task_template": template,
        "name": name,
        "labels": own_labels,
        "endpoint_spec": EndpointSpec(mode="dnsrr", ports=ports or None),
    }
