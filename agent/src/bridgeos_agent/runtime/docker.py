"""Run each skill component as a Docker container on the robot's own bridge network.

What the runtime creates, all labelled ``io.bridgeos.robot=<robot>`` and ``io.bridgeos.managed=1``:

- network ``bridgeos-<robot>``: a user-defined bridge (subnet from the ``subnet`` option,
  e.g. the robot config's ``subnets.local``), shared by all of the robot's components but its
  ROS nodes, which use the host's network (``ros_network="host"``, the default) so the ROS
  master and the Skill Router reach them at the address ROS advertises;
- volume ``bridgeos-<robot>-<skill>-<volume>`` for each of a skill's volumes, mounted at
  ``/bridgeos/volumes/<volume>`` (``BRIDGEOS_VOLUMES=/bridgeos/volumes`` in the env);
- container ``bridgeos-<robot>-<skill>-<component>``, also labelled ``io.bridgeos.skill``,
  ``io.bridgeos.component`` and ``io.bridgeos.restart`` (its restart policy), with
  ``init=True``, the CPU limit of ``resources.cpu`` and the memory limit of ``resources.ram``,
  and ``host.docker.internal`` resolving to the robot itself.

Crashed containers are restarted by the agent, not by Docker's restart policy, so every
restart is counted and reported (``runtime.lifecycle``). One thread follows Docker's event
stream for all the robot's containers (``runtime.engine``); a component's supervisor is a task
waiting for its container's death.
Docker SDK calls are blocking, so they run in one small thread pool sized to the SDK's
connection pool; stats requests, which Docker holds until its next once-a-second
collection, go straight to its unix socket from the event loop, all at once. An image the
engine lacks is pulled from the cloud's registry first (``runtime.images``).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import functools
import json
import logging
import math
import os
import re
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import docker.errors
import requests
from docker.api import APIClient
from docker.types import DeviceRequest, IPAMConfig, IPAMPool, LogConfig, Mount

from bridgeos_agent.logs.capture import DockerFollower, DockerFollowers
from bridgeos_agent.runtime.base import (
    ACTIVE,
    VOLUMES_ENV,
    ComponentSpec,
    ComponentState,
    RestartBudget,
    RuntimeFailure,
    Status,
    StatusCallback,
    Usage,
    check_ids,
)
from bridgeos_agent.runtime.engine import LABEL_ROBOT, DeathFollower, Deaths, open_client
from bridgeos_agent.runtime.images import ImagePuller, Progress, RegistryLogin
from bridgeos_agent.runtime.lifecycle import Supervised, SupervisedRuntime
from bridgeos_agent.runtime.usage import MIB, docker_usage, get_json, policy_from_label, sample_stats

__all__ = ["LABEL_MANAGED", "LABEL_ROBOT", "MIN_CPUS", "MIN_MEMORY", "VOLUMES_MOUNT", "DockerRuntime"]

logger = logging.getLogger(__name__)

LABEL_SKILL = "io.bridgeos.skill"
LABEL_COMPONENT = "io.bridgeos.component"
LABEL_MANAGED = "io.bridgeos.managed"
LABEL_RESTART = "io.bridgeos.restart"
VOLUMES_MOUNT = "/bridgeos/volumes"

MIN_MEMORY = 6 * MIB  # Docker refuses smaller memory limits
MIN_CPUS = 0.01  # and smaller CPU limits
STATS_CONCURRENCY = 256  # stats requests in flight at once (one socket each)
# How ROS nodes are networked: "host" shares the robot's stack, so the ROS master, the Skill
# Router and the node reach each other at the addresses ROS advertises (a bridge network hides
# them behind NAT and container hostnames); "bridge" keeps them on the robot network like the rest.
ROS_NETWORKS = ("host", "bridge")
DOCKER_NAME = re.compile(r"^[a-zA-Z0-9][a-zA-Z0-9_.-]*$")


@dataclass(eq=False, slots=True, kw_only=True)
class _Container(Supervised):
    """Hold what the runtime knows and owns for one component's container."""

    lock: asyncio.Lock = field(default_factory=asyncio.Lock)  # one Docker operation at a time
    container_id: str | None = None
    exited: asyncio.Future[int | None] | None = None  # resolved when the current launch dies
    cpu_seen: tuple[float, float] | None = None  # (CPU seconds, Unix time) at the last stats()
    command: list[str] | None = None  # unknown for a container adopted without saved state


class DockerRuntime(SupervisedRuntime[_Container]):
    """Launch components as Docker containers (the robot's production runtime)."""

    name = "docker"

    def __init__(
        self,
        robot: str,
        *,
        data_dir: Path,
        on_status: StatusCallback | None = None,
        subnet: str | None = None,
        docker_url: str | None = None,
        workers: int = 8,
        log_max_bytes: int = 10 * MIB,
        ros_network: str = "host",
        registry: RegistryLogin | None = None,
        disk_reserve_mb: float = 256,
    ) -> None:
        super().__init__(robot, data_dir=data_dir, on_status=on_status)
        if ros_network not in ROS_NETWORKS:
            raise ValueError(f"ros_network {ros_network!r}: use one of {', '.join(ROS_NETWORKS)}")
        if not DOCKER_NAME.fullmatch(robot):
            raise ValueError(
                f"robot id {robot!r} cannot name Docker objects: use letters, digits, '_', '.' or '-', "
                "starting with a letter or digit"
            )
        self.subnet = subnet
        self.docker_url = docker_url
        self.ros_network = ros_network
        self.log_max_bytes = log_max_bytes
        self.network = f"bridgeos-{robot}"
        self._workers = workers
        # Own pool, sized to the SDK's connection pool, so Docker calls never wait for
        # a connection and never queue behind other to_thread users.
        self._executor = ThreadPoolExecutor(max_workers=workers, thread_name_prefix=f"bridgeos-docker-{robot}")
        self._api: APIClient | None = None
        self._connect_lock = asyncio.Lock()
        self._network_ready = False
        self._network_lock = asyncio.Lock()
        self._volumes: dict[str, asyncio.Future[None]] = {}
        self._follower: DeathFollower | None = None
        self._deaths = Deaths()
        self._reconciling: set[asyncio.Task[None]] = set()
        self._socket_path: str | None = None  # Docker's unix socket, when that is how we reach it
        self._stats_slots = asyncio.Semaphore(STATS_CONCURRENCY)
        self.images = ImagePuller(registry, self._call, disk_reserve=int(disk_reserve_mb * MIB), connect=self._connect)
        self.on_pull: Callable[[str, str, str], Progress] | None = None  # (skill, component, image) -> progress
        self._followers = DockerFollowers()  # each container's log stream, once the agent captures them

    # --- names ---------------------------------------------------------------------

    def container_name(self, skill: str, component: str) -> str:
        """Return the name of a component's container."""
        return f"bridgeos-{self.robot}-{skill}-{component}"

    def volume_name(self, skill: str, volume: str) -> str:
        """Return the name of the Docker volume backing one of a skill's volumes."""
        return f"bridgeos-{self.robot}-{skill}-{volume}"

    # --- the interface ---------------------------------------------------------------

    async def _read_logs(self, skill: str, component: str, tail: int) -> list[str]:
        """Return the last ``tail`` lines of a component's container output."""
        api = await self._connect()
        try:
            raw = await self._call(api.logs, self.container_name(skill, component), tail=tail)
        except docker.errors.NotFound:
            return []
        return raw.decode("utf-8", errors="replace").splitlines()[-tail:]

    def log_sources(self) -> dict[tuple[str, str], DockerFollower]:
        """Return a follower of each container's log stream (Docker's timestamps, stdout and stderr apart)."""
        containers = {key: rec.container_id for key, rec in self._records.items() if rec.container_id}
        return self._followers.follow(self._api, containers) if self._api is not None else {}

    async def stats(self) -> dict[tuple[str, str], Usage]:
        """Measure every running container with one-shot Docker stats."""
        targets = [
            (key, rec, rec.container_id)
            for key, rec in self._records.items()
            if rec.container_id is not None and rec.state.status is Status.RUNNING
        ]
        if not targets:
            return {}
        api = await self._connect()
        samples = await asyncio.gather(
            *(self._sample_stats(api, container_id) for _, _, container_id in targets), return_exceptions=True
        )
        result: dict[tuple[str, str], Usage] = {}
        for (key, rec, _), sample in zip(targets, samples, strict=True):
            if isinstance(sample, BaseException):
                logger.debug("no stats for %s: %s", key, sample)
                continue
            raw, now = sample
            usage, cpu_seconds = docker_usage(raw)
            seen_cpu, seen_at = rec.cpu_seen or (0.0, rec.state.started_at or now)
            # A restart resets the container's counters; then count from the restart.
            if cpu_seconds < seen_cpu:
                seen_cpu, seen_at = 0.0, rec.state.started_at or seen_at
            usage.cpu = max(cpu_seconds - seen_cpu, 0.0) / max(now - seen_at, 1e-3)
            rec.cpu_seen = (cpu_seconds, now)
            result[key] = usage
        return result

    def _saved(self, rec: _Container) -> dict[str, Any] | None:
        """Keep a running container's id (it is also found again by label if this is lost)."""
        if rec.container_id is None:
            return None
        return {"container_id": rec.container_id}

    async def load_state(self, state: Mapping[str, Any]) -> list[ComponentState]:
        """Re-adopt the robot's running containers, found by label; forget the rest."""
        if self._foreign(state):
            state = {}
        api = await self._connect()
        saved = {
            (entry.get("skill"), entry.get("component")): entry
            for entry in state.get("components", ())
            if isinstance(entry, Mapping)
        }
        containers = await self._call(
            api.containers,
            filters={"label": [f"{LABEL_ROBOT}={self.robot}", f"{LABEL_MANAGED}=1"], "status": "running"},
        )
        adopted: list[ComponentState] = []
        for container in containers:
            labels = container.get("Labels") or {}
            skill, component = labels.get(LABEL_SKILL, ""), labels.get(LABEL_COMPONENT, "")
            try:
                check_ids(skill, component)
            except ValueError:
                continue
            current = self._records.get((skill, component))
            if current is not None and current.state.status in ACTIVE:
                continue
            container_id = container["Id"]
            entry = saved.get((skill, component), {})
            same = entry.get("container_id") == container_id
            rec = _Container(
                state=ComponentState(
                    skill=skill,
                    component=component,
                    status=Status.RUNNING,
                    pid_or_container_id=container_id,
                    restarts=int(entry.get("restarts") or 0) if same else 0,
                    started_at=(entry.get("started_at") if same else None) or float(container.get("Created", 0)),
                ),
                budget=RestartBudget(policy_from_label(labels.get(LABEL_RESTART))),
                container_id=container_id,
                exited=self._deaths.expect(container_id),
            )
            self._records[(skill, component)] = rec
            self._watch(rec)
            adopted.append(dataclasses.replace(rec.state))
        return adopted

    async def _release(self) -> None:
        """Stop following deaths and logs, and release the client and its threads."""
        self._followers.close()
        if self._follower is not None:
            await self._follower.close()
        await asyncio.to_thread(self._executor.shutdown)
        if self._api is not None:
            self._api.close()

    # --- Docker calls ----------------------------------------------------------------

    async def _call(self, function: Callable[..., Any], *args: Any, **kwargs: Any) -> Any:
        """Run a blocking Docker SDK call in the runtime's thread pool."""
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self._executor, functools.partial(function, *args, **kwargs))
        except requests.exceptions.ConnectionError as exc:
            raise RuntimeFailure(self._unreachable(exc)) from None

    def _unreachable(self, exc: BaseException) -> str:
        """Say that the Docker daemon cannot be reached and how to fix it."""
        where = self.docker_url or os.environ.get("DOCKER_HOST") or "unix:///var/run/docker.sock"
        return (
            f"cannot reach the Docker daemon at {where} ({exc}): start it (sudo systemctl start docker, "
            "or sudo scripts/services.sh docker), or run the agent with --runtime process"
        )

    async def _connect(self) -> APIClient:
        """Return the Docker client, connecting (and following deaths) on first use."""
        if self._api is not None:
            return self._api
        async with self._connect_lock:
            if self._api is None:
                try:
                    api, self._socket_path = await open_client(self.docker_url, self._workers, self._executor)
                except docker.errors.DockerException as exc:
                    raise RuntimeFailure(self._unreachable(exc)) from None
                self._follower = DeathFollower(
                    self.robot, asyncio.get_running_loop(), self._deaths.died, self._on_reconnect
                )
                self._follower.start(api)
                self._api = api
        return self._api

    def use_subnet(self, subnet: str | None) -> None:
        """Give the robot's network the local subnet the cloud allocated (robot config ``subnets.local``)."""
        if subnet != self.subnet:
            self.subnet = subnet
            self._network_ready = False  # checked, and recreated if it can be, before the next launch

    async def _ensure_network(self, api: APIClient) -> None:
        """Create the robot's bridge network once, on its allocated subnet."""
        if self._network_ready:
            return
        async with self._network_lock:
            if self._network_ready:
                return
            try:
                existing = await self._call(api.inspect_network, self.network)
                configs = (existing.get("IPAM") or {}).get("Config") or [{}]
                current = configs[0].get("Subnet")
                if self.subnet and current != self.subnet:
                    if existing.get("Containers"):
                        logger.warning(
                            "network %s uses %s, not the allocated %s: it is recreated once no component uses it",
                            self.network,
                            current,
                            self.subnet,
                        )
                        self._network_ready = True
                        return
                    await self._call(api.remove_network, self.network)
                    raise docker.errors.NotFound("recreated on its allocated subnet")
            except docker.errors.NotFound:
                ipam = IPAMConfig(pool_configs=[IPAMPool(subnet=self.subnet)]) if self.subnet else None
                create = functools.partial(
                    api.create_network,
                    self.network,
                    driver="bridge",
                    check_duplicate=True,
                    labels={LABEL_ROBOT: self.robot, LABEL_MANAGED: "1"},
                )
                try:
                    try:
                        await self._call(create, ipam=ipam)
                    except docker.errors.APIError as exc:
                        if ipam is None or "overlap" not in str(exc.explanation).lower():
                            raise
                        # Something on this machine holds the allocated subnet: components still run,
                        # but the cloud cannot reach them through the VPN until it is freed.
                        logger.warning(
                            "subnet %s of network %s overlaps a network on this machine (%s): using one Docker "
                            "picks; free the subnet or change the cloud's local pools (BRIDGEOS_LOCAL_POOLS)",
                            self.subnet,
                            self.network,
                            exc.explanation,
                        )
                        await self._call(create, ipam=None)
                except docker.errors.APIError as exc:
                    if exc.status_code != 409:  # 409: someone created it meanwhile
                        raise RuntimeFailure(
                            f"cannot create the robot network {self.network!r}"
                            + (f" with subnet {self.subnet}" if self.subnet else "")
                            + f": {exc.explanation}: pick a free subnet (robot config subnets.local)"
                        ) from None
            self._network_ready = True

    async def _ensure_volume(self, api: APIClient, skill: str, volume: str) -> None:
        """Create one of a skill's volumes once (creating an existing volume is a no-op)."""
        name = self.volume_name(skill, volume)
        ready = self._volumes.get(name)
        if ready is None:
            ready = self._volumes[name] = asyncio.ensure_future(
                self._call(
                    api.create_volume,
                    name,
                    labels={LABEL_ROBOT: self.robot, LABEL_SKILL: skill, LABEL_MANAGED: "1"},
                )
            )
        try:
            await asyncio.shield(ready)
        except Exception:
            self._volumes.pop(name, None)
            raise

    def _host_networked(self, spec: ComponentSpec) -> bool:
        """Say whether a component shares the robot's network stack instead of the robot network."""
        return spec.ros and self.ros_network == "host"

    def _container_config(self, api: APIClient, spec: ComponentSpec) -> dict[str, Any]:
        """Build the create-container request for a component."""
        resources = spec.resources
        host = self._host_networked(spec)
        host_config: dict[str, Any] = {
            "network_mode": "host" if host else self.network,
            "init": True,
            "mounts": [
                Mount(target=f"{VOLUMES_MOUNT}/{volume}", source=self.volume_name(spec.skill, volume), type="volume")
                for volume in spec.volumes
            ],
            # On the host's stack the robot's own names resolve already.
            "extra_hosts": None if host else {"host.docker.internal": "host-gateway"},
            "log_config": LogConfig(
                type=LogConfig.types.JSON, config={"max-size": str(self.log_max_bytes), "max-file": "2"}
            ),
        }
        if resources.cpu > 0:
            cpus = min(max(resources.cpu, MIN_CPUS), float(os.cpu_count() or 1))
            host_config["nano_cpus"] = int(cpus * 1e9)
        if resources.ram > 0:
            host_config["mem_limit"] = max(int(resources.ram * MIB), MIN_MEMORY)
        if resources.gpu > 0:
            host_config["device_requests"] = [DeviceRequest(count=resources.gpu, capabilities=[["gpu"]])]
        return {
            "image": spec.launch.image,
            "command": spec.launch.command,
            "name": self.container_name(spec.skill, spec.component),
            "environment": {**spec.launch_env(), VOLUMES_ENV: VOLUMES_MOUNT},
            "ports": None if host else list(spec.launch.ports) or None,
            "labels": {
                LABEL_ROBOT: self.robot,
                LABEL_SKILL: spec.skill,
                LABEL_COMPONENT: spec.component,
                LABEL_MANAGED: "1",
                LABEL_RESTART: json.dumps(dataclasses.asdict(spec.restart)),
            },
            "host_config": api.create_host_config(**host_config),
            "detach": True,
        }

    async def _launch(self, spec: ComponentSpec) -> tuple[str, asyncio.Future[int | None]]:
        """Create and start a container: two Docker calls once network and volumes exist."""
        who = f"component {spec.skill}/{spec.component}"
        image = spec.launch.image
        if not image:
            raise RuntimeFailure(
                f"{who} has no image for the docker runtime: add an 'image' to its robot launch spec, "
                "or run the agent with --runtime process"
            )
        api = await self._connect()
        try:
            if not self._host_networked(spec):
                await self._ensure_network(api)
            for volume in spec.volumes:
                await self._ensure_volume(api, spec.skill, volume)
        except docker.errors.APIError as exc:
            raise RuntimeFailure(f"{who}: Docker could not prepare its network or volumes: {exc.explanation}") from None
        config = self._container_config(api, spec)
        try:
            try:
                container_id, running = await self._create(api, config)
            except docker.errors.ImageNotFound:  # the first start of this image on the robot: pull it
                progress = self.on_pull(spec.skill, spec.component, image) if self.on_pull else None
                await self.images.ensure(api, image, who, progress)
                container_id, running = await self._create(api, config)
        except docker.errors.ImageNotFound:
            raise RuntimeFailure(
                f"{who}: image {image!r} went from this robot as it started: build or pull it again "
                f"(docker/build-images.sh builds the bridgeos/* images)"
            ) from None
        except docker.errors.APIError as exc:
            raise RuntimeFailure(f"{who}: Docker could not create its container: {exc.explanation}") from None
        exited = self._deaths.expect(container_id)
        if running:
            return container_id, exited
        try:
            await self._call(api.start, container_id)
        except docker.errors.APIError as exc:
            self._deaths.forget(container_id)
            with contextlib.suppress(docker.errors.APIError, RuntimeFailure):
                await self._call(api.remove_container, container_id, force=True, v=True)
            raise RuntimeFailure(
                f"{who}: Docker could not start {image!r}: {exc.explanation}: fix the command "
                f"({spec.launch.command!r}) in the skill's robot launch spec"
            ) from None
        return container_id, exited

    async def _create(self, api: APIClient, config: dict[str, Any]) -> tuple[str, bool]:
        """Create a container; return its id and whether it is one of ours already running."""
        try:
            return (await self._call(api.create_container, **config))["Id"], False
        except docker.errors.APIError as exc:
            if exc.status_code != 409:
                raise
        # The name is taken, e.g. by a container left from an earlier agent.
        info = await self._call(api.inspect_container, config["name"])
        labels = info.get("Config", {}).get("Labels") or {}
        if info.get("State", {}).get("Running") and labels.get(LABEL_ROBOT) == self.robot:
            return info["Id"], True
        await self._call(api.remove_container, info["Id"], force=True, v=True)
        return (await self._call(api.create_container, **config))["Id"], False

    async def _sample_stats(self, api: APIClient, container_id: str) -> tuple[dict[str, Any], float]:
        """Take one stats sample of a container and note when."""
        # Docker answers a stats request at its next collection tick, up to a second
        # later, whatever one_shot says; so ask for all containers at once, straight on
        # the unix socket, rather than a pool's worth of threads per second.
        if self._socket_path is None:
            return await self._call(sample_stats, api, container_id)
        url = f"/v{api.api_version}/containers/{container_id}/stats?stream=0&one-shot=1"
        async with self._stats_slots:
            raw = await get_json(self._socket_path, url)
        return raw, time.time()

    async def _stop_container(self, container_id: str, timeout: float) -> int | None:
        """Stop and remove a container; return its exit code."""
        api = await self._connect()
        self._deaths.forget(container_id)
        code = None
        try:
            await self._call(api.stop, container_id, timeout=math.ceil(timeout))
            code = (await self._call(api.wait, container_id)).get("StatusCode")
            await self._call(api.remove_container, container_id, force=True, v=True)
        except docker.errors.NotFound:
            pass
        except docker.errors.APIError as exc:
            raise RuntimeFailure(f"Docker could not stop container {container_id[:12]}: {exc.explanation}") from None
        self._deaths.forget_unclaimed(container_id)
        return code

    # --- supervision -------------------------------------------------------------------

    def _on_reconnect(self) -> None:
        """Check every watched container after the event stream was down: deaths may be lost."""
        task = asyncio.create_task(self._reconcile(self._deaths.watched()), name="bridgeos-docker-reconcile")
        self._reconciling.add(task)
        task.add_done_callback(self._reconciling.discard)

    async def _reconcile(self, container_ids: list[str]) -> None:
        """Resolve the death of watched containers that stopped while we were not listening."""
        api = await self._connect()
        for container_id in container_ids:
            try:
                info = await self._call(api.inspect_container, container_id)
            except docker.errors.NotFound:
                self._deaths.died(container_id, None)
                continue
            except (docker.errors.APIError, RuntimeFailure) as exc:
                logger.warning("cannot check container %s: %s", container_id[:12], exc)
                continue
            if not info.get("State", {}).get("Running"):
                self._deaths.died(container_id, info.get("State", {}).get("ExitCode"))

    def _guard(self, rec: _Container) -> asyncio.Lock:
        """Serialise the Docker operations on one container."""
        return rec.lock

    def _new_record(self, spec: ComponentSpec) -> _Container:
        """Return the record of a container about to be created."""
        return _Container(
            state=ComponentState(skill=spec.skill, component=spec.component, status=Status.STARTING),
            budget=RestartBudget(spec.restart),
            command=spec.launch.command,
        )

    async def _launch_first(self, rec: _Container, spec: ComponentSpec) -> None:
        """Create and start the component's container."""
        container_id, rec.exited = await self._launch(spec)
        rec.container_id = container_id
        state = rec.state
        state.pid_or_container_id = container_id
        state.status = Status.RUNNING
        state.started_at = time.time()

    async def _relaunch(self, rec: _Container) -> None:
        """Start the crashed container again."""
        state = rec.state
        container_id = rec.container_id
        assert container_id is not None  # supervised only once created
        who = f"component {state.skill}/{state.component}"
        async with rec.lock:
            rec.exited = self._deaths.expect(container_id)
            try:
                api = await self._connect()
                await self._call(api.start, container_id)
            except (docker.errors.APIError, RuntimeFailure) as exc:
                self._deaths.forget(container_id)
                raise RuntimeFailure(f"{who}: cannot restart its container: {exc}") from None
        state.status = Status.RUNNING
        state.exit_code = None
        state.message = None
        state.started_at = time.time()

    def _exited(self, rec: _Container) -> asyncio.Future[int | None] | None:
        """Return the future of the container's death."""
        return rec.exited

    def _command(self, rec: _Container) -> list[str] | None:
        """Return the container's command (docker-init runs it: a missing one shows as exit 127)."""
        return rec.command

    async def _aside(self, rec: _Container, aside: bool) -> None:
        """Rename the container, so that a new version's can take its name (or take the name back)."""
        if rec.container_id is not None:
            name = self.container_name(rec.state.skill, rec.state.component)
            api = await self._connect()
            await self._call(api.rename, rec.container_id, f"{name}-aside" if aside else name)

    async def _end(self, rec: _Container, timeout: float) -> None:
        """Stop and remove the container."""
        if rec.container_id is not None:
            rec.state.exit_code = await self._stop_container(rec.container_id, timeout)
