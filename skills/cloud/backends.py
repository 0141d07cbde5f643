"""Pick the configured cloud runtime backend (BRIDGEOS_CLOUD_RUNTIME): swarm, docker or process."""

from __future__ import annotations

from pathlib import Path

from django.conf import settings

from bridgeos_cloud.env import ConfigError

from .docker import CloudDockerRuntime
from .process import CloudProcessRuntime
from .runtime import RUNTIMES, CloudRuntime, runtime_name
from .swarm import SwarmRuntime


def create_cloud_runtime(robot: str, name: str | None = None) -> CloudRuntime:
    """Build the configured cloud runtime (BRIDGEOS_CLOUD_RUNTIME) for one robot."""
    name = name or runtime_name()
    data_dir = Path(settings.DATA_DIR) / "cloud" / "runtime"
    if name == "swarm":
        return SwarmRuntime(robot, data_dir=data_dir)
    if name == "docker":
        return CloudDockerRuntime(robot, data_dir=data_dir)
    if name == "process":
        return CloudProcessRuntime(robot, data_dir=data_dir)
    raise ConfigError(f"unknown cloud runtime {name!r}: use one of {', '.join(RUNTIMES)}")
