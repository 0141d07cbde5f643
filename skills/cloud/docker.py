"""Run cloud components as plain containers on one Docker engine: the agent's DockerRuntime, for the cloud.

For a cloud without Swarm. Each copy is a container named like the Swarm services
(``bos-<robot>-<skill>-<component>-<hash>``) on the robot's cloud bridge network, with its
ports published on host ports the engine picks, or with host networking for ROS nodes.
Its labels carry this cloud's id and never ``io.bridgeos.managed=1``: a robot-side agent on the
same engine never adopts a cloud copy. Containers are found by name and label, so any worker
process can stop, restart or inspect what another one launched.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import docker.errors
from docker.api import APIClient
from docker.types import IPAMConfig, IPAMPool, Mount

from bridgeos_agent.runtime.base import (
    ComponentSpec,
    ComponentState,
    RuntimeFailure,
    Status,
    Usage,
    absent,
    check_ids,
)
from bridgeos_agent.runtime.docker import VOLUMES_MOUNT, DockerRuntime
from bridgeos_agent.runtime.usage import cpu_share, docker_usage

from .runtime import (
    DISCOVERY_COMPONENT,
    KIND_COMPONENT,
    KIND_ROS2_DISCOVERY,
    KIND_ROS_MASTER,
    LABEL_CLOUD,
    LABEL_COMPONENT,
    LABEL_KIND,
    LABEL_ROBOT,
    LABEL_SKILL,
    LABEL_TOKEN,
    MASTER_COMPONENT,
    NO_RESTARTS,
    CloudRuntime,
    CloudSpec,
    EngineBusy,
    Observed,
    cloud_id,
    labels,
    object_name,
    ros_networking,
    volumes_root,
)

__all__ = ["CloudDockerRuntime"]


class CloudDockerRuntime(DockerRuntime, CloudRuntime):
    """Launch a robot's cloud components as containers on one engine."""

    name = "docker"

    def __init__(self, robot: str, *, data_dir: Path, docker_url: str | None = None) -> None:
        DockerRuntime.__init__(self, robot, data_dir=data_dir, docker_url=docker_url)
        CloudRuntime.__init__(self, robot, data_dir=data_dir)
        self.network = object_name(robot, kind="network")

    # --- names -----------------------------------------------------------------------

    def container_name(self, skill: str, component: str) -> str:
        """Return the name of a component's cloud container."""
        return object_name(self.robot, skill, component)

    @property
    def master_name(self) -> str:
        """Return the name of the robot's ROS master container."""
        return object_name(self.robot, kind=KIND_ROS_MASTER)

    # --- the agent's interface, by name rather than by in-memory record ----------------

    async def start(self, spec: ComponentSpec) -> ComponentState:
        """Create and start the copy's container, or adopt it if it runs (idempotent)."""
        check_ids(spec.skill, spec.component, spec.volumes)
        if not self._host_networked(spec):
            await self.ensure_network()
        await asyncio.to_thread(self._make_volume_dirs, spec)
        return await DockerRuntime.start(self, dataclasses.replace(spec, restart=NO_RESTARTS))

    async def stop(self, skill: str, component: str, timeout: float = 10.0) -> ComponentState:
        """Stop and remove the copy's container, whoever started it."""
        check_ids(skill, component)
        rec = self._records.pop((skill, component), None)
        if rec is not None and rec.supervisor is not None:
            rec.supervisor.cancel()
            await asyncio.wait([rec.supervisor])
        await self._remove_named(self.container_name(skill, component), timeout)
        return ComponentState(skill=skill, component=component, status=Status.STOPPED)

    async def status(self, skill: str, component: str) -> ComponentState:
        """Return the state of the copy's container."""
        check_ids(skill, component)
        info = await self._inspect(self.container_name(skill, component))
        return absent(skill, component) if info is None else _container_state(skill, component, info)

    async def stats(self) -> dict[tuple[str, str], Usage]:
        """Measure the robot's running copies (CPU over Docker's one-second sampling)."""
        api = await self._connect()
        containers = await self._call(
            api.containers, filters={"label": [*self._own_labels(), f"{LABEL_KIND}={KIND_COMPONENT}"]}
        )
        result: dict[tuple[str, str], Usage] = {}
        samples = await asyncio.gather(
            *(self._call(api.stats, c["Id"], stream=False) for c in containers), return_exceptions=True
        )
        for container, raw in zip(containers, samples, strict=True):
            if isinstance(raw, BaseException):
                continue
            usage, _ = docker_usage(raw)
            usage.cpu = cpu_share(raw)
            result[(container["Labels"].get(LABEL_SKILL, ""), container["Labels"].get(LABEL_COMPONENT, ""))] = usage
        return result

    def get_state(self) -> dict[str, Any]:
        """Return nothing to keep: containers are found again by name and label."""
        return {"runtime": self.name, "robot": self.robot, "components": []}

    async def load_state(self, state: Mapping[str, Any]) -> list[ComponentState]:
        """Return the robot's running copies, found by label."""
        return [
            ComponentState(skill=o.skill, component=o.component, status=o.status, pid_or_container_id=o.id)
            for o in await self.observe()
            if o.robot == self.robot and o.kind == KIND_COMPONENT and o.status is Status.RUNNING
        ]

    # --- the cloud's extras --------------------------------------------------------------

    async def ensure_network(self) -> str:
        """Create the robot's cloud bridge network once."""
        api = await self._connect()
        if not self._network_ready:
            async with self._network_lock:
                found = await self._call(api.networks, names=[self.network])
                if not any(n.get("Name") == self.network for n in found):
                    ipam = IPAMConfig(pool_configs=[IPAMPool(subnet=self.subnet)]) if self.subnet else None
                    try:
                        await self._call(
                            api.create_network,
                            self.network,
                            driver="bridge",
                            check_duplicate=True,
                            ipam=ipam,
                            labels=labels(self.robot, kind="network"),
                        )
                    except docker.errors.APIError as exc:
                        if exc.status_code != 409:
                            # A deleted robot's network may still hold the subnet: the reconciler frees it.
                            failure = EngineBusy if "overlap" in str(exc.explanation) else RuntimeFailure
                            raise failure(
                                f"cannot create the robot's cloud network {self.network} "
                                f"(subnet {self.subnet or 'any'}): {exc.explanation}"
                            ) from None
                self._network_ready = True
        return self.network

    async def remove_network(self) -> None:
        """Remove the robot's cloud network."""
        await self.remove_network_named(self.network)

    async def networks(self) -> dict[str, str]:
        """Map robot id to network name for every network of this cloud."""
        api = await self._connect()
        wanted = [f"{LABEL_CLOUD}={cloud_id()}", f"{LABEL_KIND}=network"]
        found = await self._call(api.networks, filters={"label": wanted})
        return {n["Labels"].get(LABEL_ROBOT, ""): n["Name"] for n in found}

    async def remove_network_named(self, name: str) -> None:
        """Remove a network by name, if it is there and unused."""
        api = await self._connect()
        with contextlib.suppress(docker.errors.NotFound, docker.errors.APIError):
            await self._call(api.remove_network, name)

    async def wait_running(self, skill: str, component: str, timeout: float) -> ComponentState:
        """Return the container's state: it runs once started, or it died already."""
        state = await self.status(skill, component)
        if state.status is not Status.RUNNING:
            state.status = Status.FAILED
            logs = await self.logs(skill, component, 5)
            state.message = state.message or ("the container exited at once: " + " | ".join(logs))[-500:]
        return state

    async def endpoint(self, spec: ComponentSpec) -> dict[str, Any]:
        """Return the container id, the cloud host and the host ports the engine published."""
        info = await self._inspect(self.container_name(spec.skill, spec.component))
        result: dict[str, Any] = {"runtime": self.name, "address": self.host}
        if info is None:
            return result
        result["id"] = info["Id"][:64]
        if self._host_networked(spec):
            result["ports"] = {str(port): port for port in spec.launch.ports}
            return result
        bound = (info.get("NetworkSettings") or {}).get("Ports") or {}
        ports = {}
        for key, bindings in bound.items():
            port, _, protocol = key.partition("/")
            # IPv4 and IPv6 may be published on different host ports: robots get the IPv4 one.
            ipv4 = [b for b in bindings or () if b.get("HostIp") in ("0.0.0.0", "")]
            if protocol == "tcp" and ipv4:
                ports[port] = int(ipv4[0]["HostPort"])
        result["ports"] = ports
        return result

    async def restart(self, spec: ComponentSpec) -> ComponentState:
        """Start the copy afresh: remove what is left of the crashed container, create it again."""
        await self.stop(spec.skill, spec.component)
        return await self.start(spec)

    async def start_ros_master(self, port: int) -> ComponentState:
        """Run ``rosmaster --core -p PORT`` from the ROS image with host networking."""
        from django.conf import settings

        return await self._start_host_container(
            KIND_ROS_MASTER,
            MASTER_COMPONENT,
            settings.BRIDGEOS["CLOUD_ROS_IMAGE"],
            ["rosmaster", "--core", "-p", str(port)],
            {"ROS_MASTER_URI": f"http://{self.host}:{port}", "ROS_HOME": "/tmp/ros"},
            "ROS master",
        )

    async def start_discovery_server(self, host: str, port: int) -> ComponentState:
        """Run Fast DDS's ``fast-discovery-server`` from the ROS 2 image with host networking."""
        from django.conf import settings

        return await self._start_host_container(
            KIND_ROS2_DISCOVERY,
            DISCOVERY_COMPONENT,
            settings.BRIDGEOS["CLOUD_ROS2_IMAGE"],
            ["fast-discovery-server", "-i", "0", "-l", host, "-p", str(port)],
            {},
            "ROS 2 discovery server",
        )

    async def _start_host_container(
        self, kind: str, component: str, image: str, command: list[str], env: dict[str, str], what: str
    ) -> ComponentState:
        """Run one of the robot's host-networked services (idempotent: a running one is kept)."""
        api = await self._connect()
        name = object_name(self.robot, kind=kind)
        info = await self._inspect(name)
        if info is not None and (info.get("State") or {}).get("Running"):
            return _container_state("ros", component, info)
        if info is not None:
            await self._remove_named(name, 1.0)
        config = {
            "image": image,
            "command": command,
            "name": name,
            "environment": env,
            "labels": labels(self.robot, kind=kind),
            "host_config": api.create_host_config(network_mode="host", init=True),
            "detach": True,
        }
        try:
            container_id = (await self._call(api.create_container, **config))["Id"]
            await self._call(api.start, container_id)
        except docker.errors.APIError as exc:
            raise RuntimeFailure(f"robot {self.robot}: Docker refused its {what}: {exc.explanation}") from None
        info = await self._inspect(name)
        return absent("ros", component) if info is None else _container_state("ros", component, info)

    async def stop_ros_master(self) -> None:
        """Stop and remove the robot's ROS master container."""
        await self._remove_named(self.master_name, 10.0)

    async def stop_discovery_server(self) -> None:
        """Stop and remove the robot's ROS 2 discovery server container."""
        await self._remove_named(object_name(self.robot, kind=KIND_ROS2_DISCOVERY), 10.0)

    async def observe(self) -> list[Observed]:
        """List every container of this cloud (running or not), for every robot."""
        api = await self._connect()
        containers = await self._call(api.containers, all=True, filters={"label": f"{LABEL_CLOUD}={cloud_id()}"})
        found = []
        for container in containers:
            own = container.get("Labels") or {}
            running = container.get("State") == "running"
            code = None
            if not running:
                info = await self._inspect(container["Id"])
                code = ((info or {}).get("State") or {}).get("ExitCode")
            found.append(
                Observed(
                    robot=own.get(LABEL_ROBOT, ""),
                    skill=own.get(LABEL_SKILL, ""),
                    component=own.get(LABEL_COMPONENT, ""),
                    kind=own.get(LABEL_KIND, KIND_COMPONENT),
                    status=Status.RUNNING if running else (Status.EXITED if code == 0 else Status.FAILED),
                    id=(container.get("Names") or [container["Id"]])[0].lstrip("/"),
                    token=own.get(LABEL_TOKEN, ""),
                    exit_code=code,
                    labels=own,
                )
            )
        return found

    async def remove(self, observed: Observed) -> None:
        """Stop and remove an orphan container by name."""
        await self._remove_named(str(observed.id), 10.0)

    # --- Docker calls --------------------------------------------------------------------

    def _own_labels(self) -> list[str]:
        return [f"{LABEL_CLOUD}={cloud_id()}", f"{LABEL_ROBOT}={self.robot}"]

    def _host_networked(self, spec: ComponentSpec) -> bool:
        return isinstance(spec, CloudSpec) and spec.ros and ros_networking() == "host"

    def _make_volume_dirs(self, spec: ComponentSpec) -> None:
        for volume in spec.volumes:
            (volumes_root() / self.robot / spec.skill / volume).mkdir(parents=True, exist_ok=True)

    def _container_config(self, api: APIClient, spec: ComponentSpec) -> dict[str, Any]:
        """Build the agent's container request, then make it a cloud copy's."""
        config = DockerRuntime._container_config(self, api, spec)
        host = self._host_networked(spec)
        own_labels = labels(self.robot, spec.skill, spec.component)
        if isinstance(spec, CloudSpec) and spec.token:
            own_labels[LABEL_TOKEN] = spec.token
        host_config = dict(config["host_config"])
        host_config["NetworkMode"] = "host" if host else self.network
        host_config["Mounts"] = [
            Mount(
                target=f"{VOLUMES_MOUNT}/{volume}",
                source=str(volumes_root() / self.robot / spec.skill / volume),
                type="bind",
            )
            for volume in spec.volumes
        ]
        if not host and spec.launch.ports:
            host_config["PortBindings"] = {f"{port}/tcp": [{"HostPort": ""}] for port in spec.launch.ports}
        if host:
            host_config.pop("ExtraHosts", None)  # the host's own names resolve already
        config.update(labels=own_labels, host_config=host_config)
        return config

    async def _inspect(self, name: str) -> dict[str, Any] | None:
        api = await self._connect()
        try:
            return await self._call(api.inspect_container, name)
        except docker.errors.NotFound:
            return None

    async def _remove_named(self, name: str, timeout: float) -> None:
        api = await self._connect()
        try:
            await self._call(api.stop, name, timeout=math.ceil(timeout))
        except docker.errors.NotFound:
            return
        except docker.errors.APIError:
            pass  # already stopping or dead: remove it anyway
        with contextlib.suppress(docker.errors.NotFound):
            await self._call(api.remove_container, name, force=True, v=True)


def _container_state(skill: str, component: str, info: Mapping[str, Any]) -> ComponentState:
    """Map an inspected container to a component's state."""
    state = info.get("State") or {}
    if state.get("Running"):
        status = Status.RUNNING
    elif state.get("Status") in ("created", "restarting"):
        status = Status.STARTING
    else:
        status = Status.EXITED if state.get("ExitCode") == 0 else Status.FAILED
    return ComponentState(
        skill=skill,
        component=component,
        status=status,
        pid_or_container_id=info.get("Id"),
        exit_code=None if status is Status.RUNNING else state.get("ExitCode"),
        message=state.get("Error") or None,
    )
