"""Run cloud components as processes on the cloud host: the agent's ProcessRuntime, for the cloud.

The embedded default (``make run`` without Swarm). Each copy is a process group of its own
under ``DATA_DIR/cloud/runtime``, with its Skill's volumes in the cloud volume directory.
Processes carry their identity in their environment (``BRIDGEOS_CLOUD_ID`` and
``BRIDGEOS_CLOUD_KEY``), the way containers carry labels: any worker process finds them
again by reading /proc, so a copy launched by a worker that died is never orphaned and never
launched twice. A host process shares the host's network: its ports are the host's.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import os
import signal
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import psutil
from django.conf import settings

from bridgeos_agent.ros2graph import discovery_server_command
from bridgeos_agent.runtime.base import (
    ComponentSpec,
    ComponentState,
    RuntimeFailure,
    Status,
    Usage,
    absent,
    check_ids,
)
from bridgeos_agent.runtime.groups import adopt, signal_group
from bridgeos_agent.runtime.process import ProcessRuntime
from bridgeos_agent.runtime.usage import measure
from bridgeos_agent.skillconfig import ComponentResources, LaunchSpec

from .runtime import (
    DISCOVERY_COMPONENT,
    KIND_COMPONENT,
    KIND_ROS2_DISCOVERY,
    KIND_ROS_MASTER,
    MASTER_COMPONENT,
    NO_RESTARTS,
    CloudRuntime,
    Observed,
    cloud_id,
    volumes_root,
)

__all__ = ["CloudProcessRuntime"]

ENV_CLOUD = "BRIDGEOS_CLOUD_ID"
ENV_KEY = "BRIDGEOS_CLOUD_KEY"  # kind/robot/skill/component
ROSMASTER = "/usr/bin/rosmaster"
HOST_PYTHON = "/usr/bin/python3"  # Debian's, which has the ROS modules


def _key(kind: str, robot: str, skill: str, component: str) -> str:
    return f"{kind}/{robot}/{skill}/{component}"


class CloudProcessRuntime(ProcessRuntime, CloudRuntime):
    """Launch a robot's cloud components as local process groups."""

    name = "process"

    def __init__(self, robot: str, *, data_dir: Path) -> None:
        ProcessRuntime.__init__(self, robot, data_dir=Path(data_dir) / "process" / robot)
        self.host = settings.BRIDGEOS["CLOUD_HOST"]

    def volumes_dir(self, skill: str) -> Path:
        """Return the cloud directory holding one of the robot's Skills' volumes."""
        return volumes_root() / self.robot / skill

    # --- the agent's interface, made to find copies other workers launched -------------

    async def start(self, spec: ComponentSpec) -> ComponentState:
        """Launch the copy unless a process of it runs already (whoever launched it)."""
        check_ids(spec.skill, spec.component, spec.volumes)
        found = await self._find(KIND_COMPONENT, spec.skill, spec.component)
        if found is not None:
            return ComponentState(
                skill=spec.skill, component=spec.component, status=Status.RUNNING, pid_or_container_id=found.pid
            )
        marked = _marked(spec, _key(KIND_COMPONENT, self.robot, spec.skill, spec.component))
        return await ProcessRuntime.start(self, marked)

    async def stop(self, skill: str, component: str, timeout: float = 10.0) -> ComponentState:
        """Stop the copy's process group, found by its marker."""
        check_ids(skill, component)
        await self._terminate_found(KIND_COMPONENT, skill, component, timeout)
        with contextlib.suppress(KeyError):
            del self._records[(skill, component)]
        return ComponentState(skill=skill, component=component, status=Status.STOPPED)

    async def status(self, skill: str, component: str) -> ComponentState:
        """Return RUNNING with the pid if a process of the copy runs, else ABSENT."""
        found = await self._find(KIND_COMPONENT, skill, component)
        if found is None:
            return absent(skill, component)
        return ComponentState(skill=skill, component=component, status=Status.RUNNING, pid_or_container_id=found.pid)

    async def stats(self, window: float = 0.5) -> dict[tuple[str, str], Usage]:
        """Measure the robot's running copies: CPU over ``window`` seconds, memory and I/O now."""
        found = [p for p in await asyncio.to_thread(_scan) if p.robot == self.robot and p.kind == KIND_COMPONENT]
        if not found:
            return {}
        targets = [((p.skill, p.component), p.pid, {}) for p in found]
        first = await asyncio.to_thread(measure, targets)
        await asyncio.sleep(window)
        second = await asyncio.to_thread(
            measure, [(key, pid, first[key][1]) for key, pid, _ in targets if key in first]
        )
        usages = {}
        for key, (usage, _) in second.items():
            usage.cpu = max(usage.cpu, 0.0) / window
            usages[key] = usage
        return usages

    def get_state(self) -> dict[str, Any]:
        """Return nothing to keep: running copies are found by their marker."""
        return {"runtime": self.name, "robot": self.robot, "components": []}

    async def load_state(self, state: Mapping[str, Any]) -> list[ComponentState]:
        """Return the robot's running copies, found by their marker."""
        return [
            ComponentState(skill=p.skill, component=p.component, status=Status.RUNNING, pid_or_container_id=p.pid)
            for p in await asyncio.to_thread(_scan)
            if p.robot == self.robot and p.kind == KIND_COMPONENT
        ]

    # --- the cloud's extras --------------------------------------------------------------

    async def ensure_network(self) -> None:
        """Have none: host processes share the host's network."""
        return None

    async def remove_network(self) -> None:
        """Have none to remove."""

    async def networks(self) -> dict[str, str]:
        """Have none."""
        return {}

    async def remove_network_named(self, name: str) -> None:
        """Have none to remove."""

    async def wait_running(self, skill: str, component: str, timeout: float) -> ComponentState:
        """Return the copy's state: a process runs as soon as it is launched."""
        state = await self.status(skill, component)
        if state.status is Status.ABSENT:
            state.status = Status.FAILED
            logs = await self.logs(skill, component, 5)
            state.message = "the process exited at once" + (": " + " | ".join(logs)[-500:] if logs else "")
        return state

    async def endpoint(self, spec: ComponentSpec) -> dict[str, Any]:
        """Return the pid, the cloud host and the ports the process listens on (the host's)."""
        found = await self._find(KIND_COMPONENT, spec.skill, spec.component)
        info: dict[str, Any] = {"runtime": self.name, "address": self.host}
        if found is not None:
            info["id"] = str(found.pid)
        info["ports"] = {str(port): port for port in spec.launch.ports}
        return info

    async def restart(self, spec: ComponentSpec) -> ComponentState:
        """Launch the copy again (its process is gone)."""
        await self.stop(spec.skill, spec.component)
        return await self.start(spec)

    async def start_ros_master(self, port: int) -> ComponentState:
        """Run Debian's ``rosmaster --core -p PORT`` as a process of its own."""
        found = await self._find(KIND_ROS_MASTER, "ros", MASTER_COMPONENT)
        if found is not None:
            return ComponentState(
                skill="ros", component=MASTER_COMPONENT, status=Status.RUNNING, pid_or_container_id=found.pid
            )
        if not await asyncio.to_thread(os.path.exists, ROSMASTER):
            raise RuntimeFailure(
                f"no {ROSMASTER} on the cloud host: install Debian's ros-core (scripts/services.sh ros)"
            )
        spec = ComponentSpec(
            robot=self.robot,
            skill="ros",
            component=MASTER_COMPONENT,
            location="cloud",
            launch=LaunchSpec(command=[HOST_PYTHON, ROSMASTER, "--core", "-p", str(port)]),
            resources=ComponentResources(),
            env={"ROS_MASTER_URI": f"http://{self.host}:{port}", "PATH": "/usr/bin:/bin"},
            restart=NO_RESTARTS,
        )
        return await ProcessRuntime.start(
            self, _marked(spec, _key(KIND_ROS_MASTER, self.robot, "ros", MASTER_COMPONENT))
        )

    async def stop_ros_master(self) -> None:
        """Stop the robot's ROS master process."""
        await self._terminate_found(KIND_ROS_MASTER, "ros", MASTER_COMPONENT, 10.0)

    async def start_discovery_server(self, host: str, port: int) -> ComponentState:
        """Run Fast DDS's ``fast-discovery-server`` of this Python's ROS 2 wheels as a process of its own."""
        found = await self._find(KIND_ROS2_DISCOVERY, "ros", DISCOVERY_COMPONENT)
        if found is not None:
            return ComponentState(
                skill="ros", component=DISCOVERY_COMPONENT, status=Status.RUNNING, pid_or_container_id=found.pid
            )
        try:
            command, env = discovery_server_command(host, port)
        except FileNotFoundError as exc:
            raise RuntimeFailure(f"robot {self.robot}: {exc}") from None
        spec = ComponentSpec(
            robot=self.robot,
            skill="ros",
            component=DISCOVERY_COMPONENT,
            location="cloud",
            launch=LaunchSpec(command=command),
            resources=ComponentResources(),
            env={**env, "PATH": "/usr/bin:/bin"},
            restart=NO_RESTARTS,
        )
        return await ProcessRuntime.start(
            self, _marked(spec, _key(KIND_ROS2_DISCOVERY, self.robot, "ros", DISCOVERY_COMPONENT))
        )

    async def stop_discovery_server(self) -> None:
        """Stop the robot's discovery server process."""
        await self._terminate_found(KIND_ROS2_DISCOVERY, "ros", DISCOVERY_COMPONENT, 10.0)

    async def observe(self) -> list[Observed]:
        """List every process of this cloud, for every robot."""
        return [
            Observed(robot=p.robot, skill=p.skill, component=p.component, kind=p.kind, status=Status.RUNNING, id=p.pid)
            for p in await asyncio.to_thread(_scan)
        ]

    async def remove(self, observed: Observed) -> None:
        """Stop an orphan process group by pid."""
        if isinstance(observed.id, int):
            await self._terminate_pid(observed.id, 10.0)

    async def close(self, stop_components: bool = False) -> None:
        """Stop supervising (copies keep running unless asked); nothing else to release."""
        await ProcessRuntime.close(self, stop_components)

    # --- finding processes ---------------------------------------------------------------

    async def _find(self, kind: str, skill: str, component: str) -> _Found | None:
        key = _key(kind, self.robot, skill, component)
        for found in await asyncio.to_thread(_scan):
            if found.key == key:
                return found
        return None

    async def _terminate_found(self, kind: str, skill: str, component: str, timeout: float) -> None:
        # The copy of our own launch is supervised here: cancel that first, so the exit is no crash.
        comp = self._records.get((skill, component))
        if comp is not None and comp.supervisor is not None:
            comp.supervisor.cancel()
            await asyncio.wait([comp.supervisor])
        while (found := await self._find(kind, skill, component)) is not None:
            await self._terminate_pid(found.pid, timeout)

    async def _terminate_pid(self, pid: int, timeout: float) -> None:
        try:
            create_time = psutil.Process(pid).create_time()
        except psutil.Error:
            return
        proc = adopt(pid, create_time)
        if proc is None:
            signal_group(pid, signal.SIGKILL)
            return
        self._watcher.watch(proc)
        await self._terminate(proc, timeout)


class _Found:
    """One marked process group leader."""

    __slots__ = ("component", "key", "kind", "pid", "robot", "skill")

    def __init__(self, pid: int, key: str) -> None:
        self.pid = pid
        self.key = key
        self.kind, self.robot, self.skill, self.component = key.split("/", 3)


def _scan() -> list[_Found]:
    """Find the live process-group leaders that carry this cloud's marker."""
    mine = cloud_id()
    found = []
    for process in psutil.process_iter(["pid", "status"]):
        try:
            if process.info["status"] == psutil.STATUS_ZOMBIE or os.getpgid(process.pid) != process.pid:
                continue
            env = process.environ()
        except (psutil.Error, OSError):
            continue
        if env.get(ENV_CLOUD) == mine and env.get(ENV_KEY, "").count("/") == 3:
            found.append(_Found(process.pid, env[ENV_KEY]))
    return found


def _marked(spec: ComponentSpec, key: str) -> ComponentSpec:
    """Return the spec with the marker that finds its process again, and no restarts of its own."""
    return dataclasses.replace(spec, env={**spec.env, ENV_CLOUD: cloud_id(), ENV_KEY: key}, restart=NO_RESTARTS)
