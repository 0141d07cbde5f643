"""Run cloud components as Docker Swarm services (the cloud's production runtime).

Each cloud copy is a one-replica service (docker SDK), created with what works on machines
without IPVS: ``--endpoint-mode dnsrr`` (no virtual IP), ports published in host mode (no
ingress mesh) on a port the engine picks, and ``--init``. A copy joins the robot's attachable
overlay network (``bos-<robot>-…``), where its peers find it by service name; a ROS node runs
with host networking by default instead, so TCPROS peers on the robot's side of this host
reach it and it reaches them (BRIDGEOS_CLOUD_ROS_NETWORK, see the README).

Swarm never restarts a task here (restart condition ``none``): a crash leaves the task
failed for the reconciler to see, log and restart with backoff (``restart``). Skill volumes
are bind mounts of the cloud's volume directory, which volume sync keeps in step with the
robot. Every Docker SDK call blocks, so calls run in a small thread pool of the runtime's own.
A service carries the pull token its node needs for an image of the cloud's registry (swarmauth).
"""

from __future__ import annotations

import asyncio
import functools
import logging
import math
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import docker.errors
import docker.utils
import requests
from docker.api import APIClient
from docker.types import (
    ContainerSpec,
    EndpointSpec,
    IPAMConfig,
    IPAMPool,
    NetworkAttachmentConfig,
    RestartPolicy,
    TaskTemplate,
)

from bridgeos_agent.runtime.base import (
    ComponentSpec,
    ComponentState,
    RuntimeFailure,
    Status,
    Usage,
    absent,
    check_ids,
)
from bridgeos_agent.runtime.engine import open_client
from bridgeos_agent.runtime.usage import cpu_share, docker_usage, get_json

from . import swarmauth
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
from .swarmspec import STOP_GRACE_NS, log_driver, service_config, task_key, task_state

__all__ = ["SwarmRuntime"]

logger = logging.getLogger(__name__)


STATS_CONCURRENCY = 32


class SwarmRuntime(CloudRuntime):
    """Launch a robot's cloud components as Swarm services."""

    name = "swarm"

    def __init__(self, robot: str, *, data_dir: Path, docker_url: str | None = None, workers: int = 8) -> None:
        super().__init__(robot, data_dir=data_dir)
        self.docker_url = docker_url
        self.network = object_name(robot, kind="network")
        self._executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=f"bridgeos-swarm-{robot}")
        self._workers = workers
        self._api: APIClient | None = None
        self._socket_path: str | None = None
        self._network_ready = False
        self._ids: dict[str, str] = {}  # service name -> id, once known

    # --- names -----------------------------------------------------------------------

    def service_name(self, skill: str, component: str) -> str:
        """Return the service name of a component's cloud copy."""
        return object_name(self.robot, skill, component)

    @property
    def master_name(self) -> str:
        """Return the service name of the robot's ROS master."""
        return object_name(self.robot, kind=KIND_ROS_MASTER)

    # --- the agent's interface ---------------------------------------------------------

    async def start(self, spec: ComponentSpec) -> ComponentState:
        """Create the component's service, or adopt it if it exists already (idempotent)."""
        check_ids(spec.skill, spec.component, spec.volumes)
        if not spec.launch.image:
            raise RuntimeFailure(
                f"component {spec.skill}/{spec.component} has no image for the swarm runtime: "
                "add an 'image' to its cloud launch spec"
            )
        api = await self._connect()
        name = self.service_name(spec.skill, spec.component)
        existing = await self._service(name)
        if existing is None:
            network = None if self._host_networked(spec) else await self.ensure_network()
            await asyncio.to_thread(self._make_volume_dirs, spec)
            try:
                created = await self._call(
                    swarmauth.create_service,
                    api,
                    service_config(self.robot, self.service_name(spec.skill, spec.component), spec, network),
                    self._registry_auth(spec),
                )
                self._ids[name] = created["ID"]
            except docker.errors.APIError as exc:
                if exc.status_code != 409:  # 409: created meanwhile by a redelivered task
                    raise RuntimeFailure(
                        f"component {spec.skill}/{spec.component}: Swarm refused its service: {exc.explanation}"
                    ) from None
        return await self.status(spec.skill, spec.component)

    async def stop(self, skill: str, component: str, timeout: float = 10.0) -> ComponentState:
        """Remove the component's service and wait (up to ``timeout``) for its container to go."""
        check_ids(skill, component)
        await self._remove_service(self.service_name(skill, component), timeout)
        return ComponentState(skill=skill, component=component, status=Status.STOPPED)

    async def status(self, skill: str, component: str) -> ComponentState:
        """Return the state of the component's newest task."""
        check_ids(skill, component)
        task = await self._newest_task(self.service_name(skill, component))
        if task is None:
            return absent(skill, component)
        return task_state(skill, component, task)

    async def logs(self, skill: str, component: str, tail: int = 100) -> list[str]:
        """Return the last ``tail`` lines of the service's output (its earlier tasks' too)."""
        check_ids(skill, component)
        return await self._service_logs(self.service_name(skill, component), tail)

    async def stats(self) -> dict[tuple[str, str], Usage]:
        """Measure every running container of the robot's cloud copies."""
        api = await self._connect()
        containers = await self._call(
            api.containers,
            filters={"label": [*self._own_labels(), f"{LABEL_KIND}={KIND_COMPONENT}"]},
        )
        keyed = {(c["Labels"].get(LABEL_SKILL, ""), c["Labels"].get(LABEL_COMPONENT, "")): c for c in containers}
        # Each sample keeps the engine busy about a second: a few dozen at a time, not hundreds.
        slots = asyncio.Semaphore(STATS_CONCURRENCY)

        async def sample(container_id: str) -> tuple[dict[str, Any], float]:
            async with slots:
                return await self._sample(api, container_id)

        samples = await asyncio.gather(*(sample(c["Id"]) for c in keyed.values()), return_exceptions=True)
        result: dict[tuple[str, str], Usage] = {}
        for key, sample in zip(keyed, samples, strict=True):
            if isinstance(sample, BaseException):
                continue
            raw, _ = sample
            usage, _ = docker_usage(raw)
            usage.cpu = cpu_share(raw)
            result[key] = usage
        return result

    def get_state(self) -> dict[str, Any]:
        """Return nothing to keep: Swarm holds the state, found again by label."""
        return {"runtime": self.name, "robot": self.robot, "components": []}

    async def load_state(self, state: Mapping[str, Any]) -> list[ComponentState]:
        """Return the robot's running copies: Swarm keeps them, nothing needs adopting."""
        return [
            ComponentState(skill=item.skill, component=item.component, status=item.status, pid_or_container_id=item.id)
            for item in await self.observe()
            if item.robot == self.robot and item.kind == KIND_COMPONENT and item.status is Status.RUNNING
        ]

    async def close(self, stop_components: bool = False) -> None:
        """Release the client; remove the robot's services too if asked."""
        if stop_components:
            for item in await self.observe():
                if item.robot == self.robot:
                    await self.remove(item)
        await asyncio.to_thread(self._executor.shutdown)
        if self._api is not None:
            self._api.close()

    # --- the cloud's extras --------------------------------------------------------------

    async def ensure_network(self) -> str:
        """Create the robot's attachable overlay network once."""
        if self._network_ready:
            return self.network
        api = await self._connect()
        found = await self._call(api.networks, names=[self.network])
        if not any(n.get("Name") == self.network for n in found):
            ipam = IPAMConfig(pool_configs=[IPAMPool(subnet=self.subnet)]) if self.subnet else None
            for attempt in (1, 2):
                try:
                    await self._call(
                        api.create_network,
                        self.network,
                        driver="overlay",
                        attachable=True,
                        check_duplicate=True,
                        ipam=ipam,
                        labels=labels(self.robot, kind="network"),
                    )
                    break
                except docker.errors.APIError as exc:
                    if exc.status_code == 409:
                        break  # created meanwhile
                    if attempt == 1 and "overlap" in str(exc.explanation) and await self._release_subnet():
                        continue
                    subnet = f" with the robot's cloud subnet {self.subnet}" if self.subnet else ""
                    failure = EngineBusy if "overlap" in str(exc.explanation) else RuntimeFailure
                    raise failure(
                        f"cannot create the robot's cloud network {self.network}{subnet}: {exc.explanation}"
                    ) from None
        self._network_ready = True
        return self.network

    async def _release_subnet(self) -> bool:
        """Remove this cloud's network of another robot that holds our subnet; tell whether one went.

        IPAM never gives two robots one subnet, so such a network is a deleted robot's, waiting
        for the reconciler; Docker refuses while its last copies are still being removed.
        """
        api = await self._connect()
        wanted = [f"{LABEL_CLOUD}={cloud_id()}", f"{LABEL_KIND}=network"]
        released = False
        for network in await self._call(api.networks, filters={"label": wanted}):
            configs = (network.get("IPAM") or {}).get("Config") or []
            mine = network.get("Labels", {}).get(LABEL_ROBOT) == self.robot
            if not mine and any(config.get("Subnet") == self.subnet for config in configs):
                try:
                    await self._call(api.remove_network, network["Id"])
                    released = True
                except docker.errors.APIError as exc:
                    logger.info("network %s still holds %s: %s", network.get("Name"), self.subnet, exc.explanation)
        return released

    async def remove_network(self) -> None:
        """Remove the robot's overlay network (Docker refuses while something uses it)."""
        await self.remove_network_named(self.network)

    async def networks(self) -> dict[str, str]:
        """Map robot id to network name for every overlay network of this cloud."""
        api = await self._connect()
        wanted = [f"{LABEL_CLOUD}={cloud_id()}", f"{LABEL_KIND}=network"]
        found = await self._call(api.networks, filters={"label": wanted})
        return {n["Labels"].get(LABEL_ROBOT, ""): n["Name"] for n in found}

    async def remove_network_named(self, name: str) -> None:
        """Remove one network by name, if it is there and unused."""
        api = await self._connect()
        try:
            await self._call(api.remove_network, name)
        except docker.errors.NotFound:
            pass
        except docker.errors.APIError as exc:
            logger.info("network %s not removed yet: %s", name, exc.explanation)

    async def wait_running(self, skill: str, component: str, timeout: float) -> ComponentState:
        """Poll the service's newest task until it runs, fails, or ``timeout`` passes."""
        return await self._wait_task(self.service_name(skill, component), skill, component, timeout)

    async def endpoint(self, spec: ComponentSpec) -> dict[str, Any]:
        """Return the task's container id, the cloud host and the host ports the engine published."""
        task = await self._newest_task(self.service_name(spec.skill, spec.component))
        info: dict[str, Any] = {"runtime": self.name, "address": self.host}
        if task is None:
            return info
        container_id = ((task.get("Status") or {}).get("ContainerStatus") or {}).get("ContainerID")
        if container_id:
            info["id"] = container_id[:64]
        if self._host_networked(spec):
            # Host networking: the container's ports are the host's.
            info["ports"] = {str(port): port for port in spec.launch.ports}
        else:
            info["ports"] = await self._published_ports(task, container_id)
        return info

    async def restart(self, spec: ComponentSpec) -> ComponentState:
        """Force a new task for the service (its old one crashed), or create it if it is gone."""
        api = await self._connect()
        name = self.service_name(spec.skill, spec.component)
        service = await self._service(name)
        if service is None:
            return await self.start(spec)
        replaced = await self._newest_task(name)
        template = dict(service["Spec"]["TaskTemplate"])
        # A new ForceUpdate value makes Swarm replace the task even though the spec is unchanged.
        template["ForceUpdate"] = int(template.get("ForceUpdate") or 0) + 1
        try:
            # A fresh registry token with it: the one the service was created with may have expired.
            await self._call(
                swarmauth.update_service,
                api,
                service,
                {**service["Spec"], "TaskTemplate": template},
                self._registry_auth(spec),
            )
        except docker.errors.APIError as exc:
            raise RuntimeFailure(
                f"component {spec.skill}/{spec.component}: cannot restart: {exc.explanation}"
            ) from None
        # Swarm makes the new task a moment later: report it, not the failed one it replaces.
        deadline = time.monotonic() + 10
        while replaced is not None and time.monotonic() < deadline:
            task = await self._newest_task(name)
            if task is not None and task["ID"] != replaced["ID"]:
                break
            await asyncio.sleep(0.05)
        return await self.status(spec.skill, spec.component)

    async def start_ros_master(self, port: int) -> ComponentState:
        """Run ``rosmaster --core -p PORT`` from the ROS image as a host-networked service."""
        from django.conf import settings

        return await self._start_host_service(
            KIND_ROS_MASTER,
            MASTER_COMPONENT,
            settings.BRIDGEOS["CLOUD_ROS_IMAGE"],
            ["rosmaster", "--core", "-p", str(port)],
            {"ROS_MASTER_URI": f"http://{self.host}:{port}", "ROS_HOME": "/tmp/ros"},
            "ROS master",
        )

    async def start_discovery_server(self, host: str, port: int) -> ComponentState:
        """Run Fast DDS's ``fast-discovery-server`` from the ROS 2 image as a host-networked service."""
        from django.conf import settings

        return await self._start_host_service(
            KIND_ROS2_DISCOVERY,
            DISCOVERY_COMPONENT,
            settings.BRIDGEOS["CLOUD_ROS2_IMAGE"],
            ["fast-discovery-server", "-i", "0", "-l", host, "-p", str(port)],
            {},
            "ROS 2 discovery server",
        )

    async def _start_host_service(
        self, kind: str, component: str, image: str, command: list[str], env: dict[str, str], what: str
    ) -> ComponentState:
        """Run one of the robot's host-networked services (idempotent: an existing one is kept)."""
        api = await self._connect()
        name = object_name(self.robot, kind=kind)
        if await self._service(name) is None:
            container = ContainerSpec(
                image=image,
                command=command,
                env=env,
                labels=labels(self.robot, kind=kind),
                init=True,
                stop_grace_period=STOP_GRACE_NS,
            )
            template = TaskTemplate(
                container_spec=container,
                restart_policy=RestartPolicy(condition="none"),
                networks=[NetworkAttachmentConfig("host")],
                log_driver=log_driver(),
            )
            try:
                await self._call(
                    api.create_service,
                    template,
                    name=name,
                    labels=labels(self.robot, kind=kind),
                    endpoint_spec=EndpointSpec(mode="dnsrr"),
                )
            except docker.errors.APIError as exc:
                if exc.status_code != 409:
                    raise RuntimeFailure(f"robot {self.robot}: Swarm refused its {what}: {exc.explanation}") from None
        return await self._wait_task(name, "ros", component, 60.0)

    async def stop_ros_master(self) -> None:
        """Remove the robot's ROS master service."""
        await self._remove_service(self.master_name, 10.0)

    async def stop_discovery_server(self) -> None:
        """Remove the robot's ROS 2 discovery server service."""
        await self._remove_service(object_name(self.robot, kind=KIND_ROS2_DISCOVERY), 10.0)

    async def observe(self) -> list[Observed]:
        """List every service of this cloud with the state of its newest task."""
        api = await self._connect()
        services = await self._call(api.services, filters={"label": f"{LABEL_CLOUD}={cloud_id()}"})
        if not services:
            return []
        tasks = await self._call(api.tasks, filters={"label": f"{LABEL_CLOUD}={cloud_id()}"})
        newest: dict[str, dict[str, Any]] = {}
        for task in tasks:
            sid = task.get("ServiceID", "")
            if sid not in newest or task_key(task) > task_key(newest[sid]):
                newest[sid] = task
        found = []
        for service in services:
            spec_labels = (service.get("Spec") or {}).get("Labels") or {}
            task = newest.get(service["ID"])
            skill, component = spec_labels.get(LABEL_SKILL, ""), spec_labels.get(LABEL_COMPONENT, "")
            state = task_state(skill, component, task) if task else absent(skill, component)
            found.append(
                Observed(
                    robot=spec_labels.get(LABEL_ROBOT, ""),
                    skill=skill,
                    component=component,
                    kind=spec_labels.get(LABEL_KIND, KIND_COMPONENT),
                    status=state.status,
                    id=(service.get("Spec") or {}).get("Name") or service["ID"],
                    token=spec_labels.get(LABEL_TOKEN, ""),
                    exit_code=state.exit_code,
                    message=state.message,
                    labels=spec_labels,
                )
            )
        return found

    async def remove(self, observed: Observed) -> None:
        """Remove an orphan service by name."""
        await self._remove_service(str(observed.id), 10.0)

    # --- Docker calls --------------------------------------------------------------------

    def _own_labels(self) -> list[str]:
        return [f"{LABEL_CLOUD}={cloud_id()}", f"{LABEL_ROBOT}={self.robot}"]

    def _registry_auth(self, spec: ComponentSpec) -> str:
        return spec.registry_auth if isinstance(spec, CloudSpec) else ""

    def _host_networked(self, spec: ComponentSpec) -> bool:
        return isinstance(spec, CloudSpec) and spec.ros and ros_networking() == "host"

    def _make_volume_dirs(self, spec: ComponentSpec) -> None:
        for volume in spec.volumes:
            (volumes_root() / self.robot / spec.skill / volume).mkdir(parents=True, exist_ok=True)

    async def _published_ports(self, task: Mapping[str, Any], container_id: str | None) -> dict[str, int]:
        """Map container port to the host port published for IPv4.

        The engine may publish a port twice, on different host ports for IPv4 and IPv6; the
        task lists both without saying which is which, so the container's own bindings decide
        when it runs on this engine, and otherwise the first of each (the IPv4 one) is taken.
        """
        ports: dict[str, int] = {}
        if container_id:
            api = await self._connect()
            try:
                info = await self._call(api.inspect_container, container_id)
            except docker.errors.NotFound:
                info = None
            for key, bindings in (((info or {}).get("NetworkSettings") or {}).get("Ports") or {}).items():
                port, _, protocol = key.partition("/")
                ipv4 = [b for b in bindings or () if b.get("HostIp") in ("0.0.0.0", "")]
                if protocol == "tcp" and ipv4:
                    ports[port] = int(ipv4[0]["HostPort"])
            if ports:
                return ports
        for entry in ((task.get("Status") or {}).get("PortStatus") or {}).get("Ports") or []:
            if entry.get("PublishedPort") and entry.get("TargetPort"):
                ports.setdefault(str(entry["TargetPort"]), entry["PublishedPort"])
        return ports

    async def _service(self, name: str) -> dict[str, Any] | None:
        api = await self._connect()
        try:
            service = await self._call(api.inspect_service, name)
        except docker.errors.NotFound:
            self._ids.pop(name, None)
            return None
        self._ids[name] = service["ID"]
        return service

    async def _newest_task(self, name: str) -> dict[str, Any] | None:
        api = await self._connect()
        service_id = self._ids.get(name)
        if service_id is None:
            service = await self._service(name)
            if service is None:
                return None
            service_id = service["ID"]
        try:
            tasks = await self._call(api.tasks, filters={"service": service_id})
        except docker.errors.NotFound:
            return None
        # Filters match by prefix: keep the service's own tasks.
        tasks = [t for t in tasks if t.get("ServiceID") == service_id]
        return max(tasks, key=task_key) if tasks else None

    async def _wait_task(self, name: str, skill: str, component: str, timeout: float) -> ComponentState:
        deadline = time.monotonic() + timeout
        # Polled often at first: a task usually runs within a second, and every poll is one local call.
        delay = 0.03
        while True:
            task = await self._newest_task(name)
            if task is None:
                state = absent(skill, component)
            else:
                state = task_state(skill, component, task)
                if state.status in (Status.RUNNING, Status.FAILED, Status.EXITED):
                    return state
            if time.monotonic() >= deadline:
                state.status = Status.FAILED
                state.message = f"{name}: not running after {timeout:g} s ({state.message or 'no task yet'})"
                return state
            await asyncio.sleep(delay)
            delay = min(delay * 1.1, 0.25)

    async def _remove_service(self, name: str, timeout: float) -> None:
        api = await self._connect()
        self._ids.pop(name, None)
        try:
            service = await self._call(api.inspect_service, name)
        except docker.errors.NotFound:
            return
        try:
            await self._call(api.remove_service, service["ID"])
        except docker.errors.NotFound:
            return
        except docker.errors.APIError as exc:
            raise RuntimeFailure(f"Swarm could not remove {name}: {exc.explanation}") from None
        # Removal is asynchronous: wait for the task's container to be gone, so the copy is stopped.
        # Its containers on this engine are stopped right away rather than at Swarm's next pass.
        label = {"label": f"com.docker.swarm.service.id={service['ID']}"}
        local = await self._call(api.containers, filters=label)
        await asyncio.gather(
            *(self._call(api.stop, c["Id"], timeout=math.ceil(timeout)) for c in local), return_exceptions=True
        )
        deadline = time.monotonic() + timeout + 5
        while time.monotonic() < deadline:
            if not await self._call(api.containers, all=True, filters=label):
                return
            await asyncio.sleep(0.1)
        logger.warning("containers of %s still there %.0f s after its removal", name, timeout + 5)

    async def _service_logs(self, name: str, tail: int) -> list[str]:
        if tail <= 0:
            return []
        api = await self._connect()

        def read() -> list[str]:
            try:
                chunks = api.service_logs(name, stdout=True, stderr=True, tail=tail, follow=False)
                raw = b"".join(chunks)
            except docker.errors.NotFound:
                return []
            return raw.decode("utf-8", errors="replace").splitlines()[-tail:]

        return await self._call(read)

    async def _sample(self, api: APIClient, container_id: str) -> tuple[dict[str, Any], float]:
        if self._socket_path is None:
            raw = await self._call(api.stats, container_id, stream=False)
            return raw, time.time()
        url = f"/v{api.api_version}/containers/{container_id}/stats?stream=0"
        return await get_json(self._socket_path, url), time.time()

    async def _call(self, function: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self._executor, functools.partial(function, *args, **kwargs))
        except requests.exceptions.ConnectionError as exc:
            raise RuntimeFailure(f"cannot reach the Docker engine: {exc}") from None

    async def _connect(self) -> APIClient:
        if self._api is None:
            try:
                self._api, self._socket_path = await open_client(self.docker_url, self._workers, self._executor)
            except docker.errors.DockerException as exc:
                where = self.docker_url or "DOCKER_HOST or /var/run/docker.sock"
                raise RuntimeFailure(f"cannot reach the Docker engine at {where}: {exc}") from None
        return self._api
