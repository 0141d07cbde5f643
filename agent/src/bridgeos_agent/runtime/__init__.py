"""Launch a robot's skill components: as local processes or as Docker containers."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from bridgeos_agent.runtime.base import (
    ComponentSpec,
    ComponentState,
    RestartPolicy,
    Runtime,
    RuntimeFailure,
    Status,
    StatusCallback,
    Usage,
)
from bridgeos_agent.runtime.process import ProcessRuntime

__all__ = [
    "RUNTIMES",
    "ComponentSpec",
    "ComponentState",
    "ProcessRuntime",
    "RestartPolicy",
    "Runtime",
    "RuntimeFailure",
    "Status",
    "StatusCallback",
    "Usage",
    "create_runtime",
]

RUNTIMES = ("process", "docker")


def create_runtime(
    name: str,
    robot: str,
    *,
    data_dir: Path,
    on_status: StatusCallback | None = None,
    **options: Any,
) -> Runtime:
    """Build the runtime called ``name`` ('process' or 'docker') for one robot."""
    if name == "process":
        return ProcessRuntime(robot, data_dir=data_dir, on_status=on_status, **options)
    if name == "docker":
        # Imported here: the Docker SDK (and requests) is only loaded when it is used.
        from bridgeos_agent.runtime.docker import DockerRuntime

        return DockerRuntime(robot, data_dir=data_dir, on_status=on_status, **options)
    raise ValueError(f"unknown runtime {name!r}: choose one of {', '.join(RUNTIMES)}")
