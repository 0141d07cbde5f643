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
restart is counted and reported. One thread follows Docker's event stream for all the
robot's containers; a component's supervisor is a task waiting for its container's death.
Docker SDK calls are blocking, so they run in one small thread pool sized to the SDK's
connection pool; stats requests, which Docker holds until its next once-a-second
collection, go straight to its unix socket from the event loop, all at once. Images are
never pulled: no registry is reachable from a robot here.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import functools
import json
import logging
import math
import os
import re
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import docker.errors
import docker.utils
import requests
from docker.api import APIClient
from docker.types import DeviceRequest, IPAMConfig, IPAMPool, LogConfig, Mount

from bridgeos_agent.runtime.base import (
    ACTIVE,
    VOLUMES_ENV,
    ComponentSpec,
    ComponentState,
    RestartBudget,
    RestartPolicy,
    Runtime,
    RuntimeFailure,
    Status,
    StatusCallback,
    Usage,
    absent,
    check_ids,
    give_up_message,
    unrunnable,
)

__all__ = ["LABEL_MANAGED", "LABEL_ROBOT", "VOLUMES_MOUNT", "DockerRuntime"]

logger = logging.getLogger(__name__)

LABEL_ROBOT = "io.bridgeos.robot"
LABEL_SKILL = "io.bridgeos.skill"
LABEL_COMPONENT = "io.bridgeos.component"
LABEL_MANAGED = "io.bridgeos.managed"
LABEL_RESTART = "io.bridgeos.restart"
VOLUMES_MOUNT = "/bridgeos/volumes"

MIB = 1024 * 1024
MIN_MEMORY = 6 * MIB  # Docker refuses smaller memory limits
MIN_CPUS = 0.01  # and smaller CPU limits
STATS_CONCURRENCY = 256  # stats requests in flight at once (one socket each)
# How ROS nodes are networked: "host" shares the robot's stack, so the ROS master, the Skill
# Router and the node reach each other at the addresses ROS advertises (a bridge network hides
# them behind NAT and container hostnames); "bridge" keeps them on the robot network like the rest.
ROS_NETWORKS = ("host", "bridge")
DOCKER_NAME = re.compile(r"^[a-zA-Z0-9][a-zA-Z0-9_.-]*$")


@dataclass(eq=False, slots=True)
class _Container:
    """Hold what the runtime knows and owns for one component's container."""

    state: ComponentState
    budget: RestartBudget
    lock: asyncio.Lock = field(default_factory=asyncio.Lock)  # one Docker operation at a time
    container_id: str | None = None
    supervisor: asyncio.Task[None] | None = None
    stop_done: asyncio.Future[None] | None = None
    cpu_seen: tuple[float, float] | None = None  # (CPU seconds, Unix time) at the last stats()
    command: list[str] | None = None  # unknown for a container adopted without saved state


class _DeathFollower:
    """Follow the robot's container 'die' events in one thread and hand them to the loop."""

    def __init__(
        self,
        robot: str,
        loop: asyncio.AbstractEventLoop,
        on_die: Callable[[str, int | None], None],
        on_reconnect: Callable[[], None],
    ) -> None:
        self._robot = robot
        self._loop = loop
        self._on_die = on_die
        self._on_reconnect = on_reconnect
        self._closed = threading.Event()
        self._stream: Any = None
        self._thread: threading.Thread | None = None

    def start(self, api: APIClient) -> None:
        """Start following; events since this moment are delivered even if the stream lags."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(
            target=self._run, args=(api, time.time()), name=f"bridgeos-docker-events-{self._robot}", daemon=True
        )
        self._thread.start()

    def _run(self, api: APIClient, since: float) -> None:
        """Read the event stream, reconnecting with backoff when Docker goes away."""
        last_nano = 0
        delay = 0.5
        connected_before = False
        filters = {"type": "container", "event": "die", "label": f"{LABEL_ROBOT}={self._robot}"}
        while not self._closed.is_set():
            try:
                self._stream = api.events(since=f"{since:.9f}", filters=filters, decode=True)
                if self._closed.is_set():  # closed while connecting: close() saw no stream
                    self._stream.close()
                    break
                if connected_before:
                    self._post(self._on_reconnect)
                connected_before = True
                delay = 0.5
                for event in self._stream:
                    nano = int(event.get("timeNano") or 0)
                    if nano and nano <= last_nano:
                        continue  # replayed after a reconnect
                    last_nano = max(last_nano, nano)
                    since = nano / 1e9 if nano else since
                    code = (event.get("Actor") or {}).get("Attributes", {}).get("exitCode")
                    self._post(self._on_die, event.get("id", ""), int(code) if code is not None else None)
            except Exception as exc:
                if not self._closed.is_set():
                    logger.warning("Docker event stream failed (%s); reconnecting in %.1f s", exc, delay)
            if self._closed.wait(delay):
                break
            delay = min(delay * 2, 10.0)

    def _post(self, callback: Callable[..., None], *args: Any) -> None:
        """Run a callback in the event loop, unless the loop is gone."""
        with contextlib.suppress(RuntimeError):
            self._loop.call_soon_threadsafe(callback, *args)

    async def close(self) -> None:
        """Stop following and wait for the thread to end."""
        self._closed.set()
        stream = self._stream
        if stream is not None:
            with contextlib.suppress(Exception):
                stream.close()
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 5.0)


async def open_client(
    docker_url: str | None, workers: int, executor: ThreadPoolExecutor
) -> tuple[APIClient, str | None]:
    """Connect to the engine (``docker_url``, else DOCKER_HOST, else its socket) with a pool for ``workers``.

    Return the client and the engine's unix socket path (None over TCP); raise DockerException.
    """
    options: dict[str, Any] = docker.utils.kwargs_from_env()
    if docker_url:
        options["base_url"] = docker_url
    url = options.get("base_url") or "unix:///var/run/docker.sock"
    socket_path = url.removeprefix("unix://") if url.startswith("unix://") else None
    options.update(version="auto", max_pool_size=workers + 2)
    api = await asyncio.get_running_loop().run_in_executor(executor, functools.partial(APIClient, **options))
    return api, socket_path


class DockerRuntime(Runtime):
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
        self._records: dict[tuple[str, str], _Container] = {}
        self._follower: _DeathFollower | None = None
        self._waiters: dict[str, asyncio.Future[int | None]] = {}
        # Deaths nobody waited for yet (e.g. between listing and watching an adopted container).
        self._unclaimed: collections.OrderedDict[str, int | None] = collections.OrderedDict()
        self._reconciling: set[asyncio.Task[None]] = set()
        self._socket_path: str | None = None  # Docker's unix socket, when that is how we reach it
        self._stats_slots = asyncio.Semaphore(STATS_CONCURRENCY)

    # --- names ---------------------------------------------------------------------

    def container_name(self, skill: str, component: str) -> str:
        """Return the name of a component's container."""
        return f"bridgeos-{self.robot}-{skill}-{component}"

    def volume_name(self, skill: str, volume: str) -> str:
        """Return the name of the Docker volume backing one of a skill's volumes."""
        return f"bridgeos-{self.robot}-{skill}-{volume}"

    # --- the interface ---------------------------------------------------------------

    async def start(self, spec: ComponentSpec) -> ComponentState:
        """Create and start a component's container, or return its state if it runs."""
        check_ids(spec.skill, spec.component, spec.volumes)
        key = spec.key
        rec = self._records.get(key)
        while rec is not None and rec.stop_done is not None and not rec.stop_done.done():
            await asyncio.shield(rec.stop_done)
            rec = self._records.get(key)
        if rec is not None and rec.state.status in ACTIVE:
            async with rec.lock:  # a concurrent start of the same component finishes first
                return dataclasses.replace(rec.state)
        rec = _Container(
            state=ComponentState(skill=spec.skill, component=spec.component, status=Status.STARTING),
            budget=RestartBudget(spec.restart),
            command=spec.launch.command,
        )
        self._records[key] = rec
        self._notify(rec.state)
        async with rec.lock:
            try:
                container_id, exited = await self._launch(spec)
            except RuntimeFailure as exc:
                rec.state.status = Status.FAILED
                rec.state.message = str(exc)
                self._notify(rec.state)
                raise
            state = rec.state
            rec.container_id = container_id
            state.pid_or_container_id = container_id
            state.status = Status.RUNNING
            state.started_at = time.time()
            self._notify(state)
            rec.supervisor = asyncio.create_task(
                self._supervise(rec, exited), name=f"bridgeos-docker-{spec.skill}/{spec.component}"
            )
            return dataclasses.replace(state)

    async def stop(self, skill: str, component: str, timeout: float = 10.0) -> ComponentState:
        """Stop (SIGTERM, SIGKILL after ``timeout``) and remove a component's container."""
        check_ids(skill, component)
        rec = self._records.get((skill, component))
        if rec is None:
            return absent(skill, component)
        if rec.stop_done is not None:
            await asyncio.shield(rec.stop_done)
            return dataclasses.replace(rec.state)
        done = rec.stop_done = asyncio.get_running_loop().create_future()
        try:
            async with rec.lock:
                if rec.supervisor is not None:
                    # Cancelled first, so the death our stop causes is never taken for a crash.
                    rec.supervisor.cancel()
                    await asyncio.wait([rec.supervisor])
                if rec.container_id is not None:
                    rec.state.exit_code = await self._stop_container(rec.container_id, timeout)
                rec.state.status = Status.STOPPED
                self._notify(rec.state)
        except BaseException:
            rec.stop_done = None  # let a later stop() try again
            raise
        finally:
            done.set_result(None)
        return dataclasses.replace(rec.state)

    async def status(self, skill: str, component: str) -> ComponentState:
        """Return a component's current state (status 'absent' if unknown)."""
        rec = self._records.get((skill, component))
        return absent(skill, component) if rec is None else dataclasses.replace(rec.state)

    async def logs(self, skill: str, component: str, tail: int = 100) -> list[str]:
        """Return the last ``tail`` lines of a component's container output."""
        check_ids(skill, component)
        if tail <= 0:
            return []
        api = await self._connect()
        try:
            raw = await self._call(api.logs, self.container_name(skill, component), tail=tail)
        except docker.errors.NotFound:
            return []
        return raw.decode("utf-8", errors="replace").splitlines()[-tail:]

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
            usage, cpu_seconds = _usage(raw)
            seen_cpu, seen_at = rec.cpu_seen or (0.0, rec.state.started_at or now)
            # A restart resets the container's counters; then count from the restart.
            if cpu_seconds < seen_cpu:
                seen_cpu, seen_at = 0.0, rec.state.started_at or seen_at
            usage.cpu = max(cpu_seconds - seen_cpu, 0.0) / max(now - seen_at, 1e-3)
            rec.cpu_seen = (cpu_seconds, now)
            result[key] = usage
        return result

    def get_state(self) -> dict[str, Any]:
        """Return the running containers (also found again by label if this is lost)."""
        return {
            "runtime": self.name,
            "robot": self.robot,
            "components": [
                {
                    "skill": skill,
                    "component": component,
                    "container_id": rec.container_id,
                    "restarts": rec.state.restarts,
                    "started_at": rec.state.started_at,
                }
                for (skill, component), rec in self._records.items()
                if rec.container_id is not None and rec.state.status is Status.RUNNING
            ],
        }

    async def load_state(self, state: Mapping[str, Any]) -> list[ComponentState]:
        """Re-adopt the robot's running containers, found by label; forget the rest."""
        if state.get("runtime", self.name) != self.name:
            logger.warning("ignoring saved state of the %r runtime", state.get("runtime"))
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
                budget=RestartBudget(_policy_from_label(labels.get(LABEL_RESTART))),
                container_id=container_id,
            )
            self._records[(skill, component)] = rec
            rec.supervisor = asyncio.create_task(
                self._supervise(rec, self._expect_death(container_id)), name=f"bridgeos-docker-{skill}/{component}"
            )
            adopted.append(dataclasses.replace(rec.state))
        return adopted

    async def close(self, stop_components: bool = False) -> None:
        """Stop supervising and release the client; stop the containers too if asked."""
        if stop_components:
            await asyncio.gather(*(self.stop(*key) for key, rec in self._records.items() if rec.state.status in ACTIVE))
        tasks = [rec.supervisor for rec in self._records.values() if rec.supervisor is not None]
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.wait(tasks)
        self._records.clear()
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
                self._follower = _DeathFollower(
                    self.robot, asyncio.get_running_loop(), self._on_death, self._on_reconnect
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
            container_id, running = await self._create(api, config)
        except docker.errors.ImageNotFound:
            raise RuntimeFailure(
                f"{who}: image {image!r} is not on this robot and no registry is reachable: build it here "
                f"(docker/build-images.sh builds the bridgeos/* images; otherwise docker build -t {image} DIR)"
            ) from None
        except docker.errors.APIError as exc:
            raise RuntimeFailure(f"{who}: Docker could not create its container: {exc.explanation}") from None
        exited = self._expect_death(container_id)
        if running:
            return container_id, exited
        try:
            await self._call(api.start, container_id)
        except docker.errors.APIError as exc:
            self._waiters.pop(container_id, None)
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
            return await self._call(_sample_stats, api, container_id)
        url = f"/v{api.api_version}/containers/{container_id}/stats?stream=0&one-shot=1"
        async with self._stats_slots:
            raw = await _get_json(self._socket_path, url)
        return raw, time.time()

    async def _stop_container(self, container_id: str, timeout: float) -> int | None:
        """Stop and remove a container; return its exit code."""
        api = await self._connect()
        self._waiters.pop(container_id, None)
        code = None
        try:
            await self._call(api.stop, container_id, timeout=math.ceil(timeout))
            code = (await self._call(api.wait, container_id)).get("StatusCode")
            await self._call(api.remove_container, container_id, force=True, v=True)
        except docker.errors.NotFound:
            pass
        except docker.errors.APIError as exc:
            raise RuntimeFailure(f"Docker could not stop container {container_id[:12]}: {exc.explanation}") from None
        self._unclaimed.pop(container_id, None)
        return code

    # --- supervision -------------------------------------------------------------------

    def _expect_death(self, container_id: str) -> asyncio.Future[int | None]:
        """Return a future resolved with the container's exit code when it dies."""
        future: asyncio.Future[int | None] = asyncio.get_running_loop().create_future()
        if container_id in self._unclaimed:
            future.set_result(self._unclaimed.pop(container_id))
        else:
            self._waiters[container_id] = future
        return future

    def _on_death(self, container_id: str, code: int | None) -> None:
        """Deliver a container's death to whoever waits for it."""
        future = self._waiters.pop(container_id, None)
        if future is not None and not future.done():
            future.set_result(code)
            return
        self._unclaimed[container_id] = code
        while len(self._unclaimed) > 256:
            self._unclaimed.popitem(last=False)

    def _on_reconnect(self) -> None:
        """Check every watched container after the event stream was down: deaths may be lost."""
        task = asyncio.create_task(self._reconcile(list(self._waiters)), name="bridgeos-docker-reconcile")
        self._reconciling.add(task)
        task.add_done_callback(self._reconciling.discard)

    async def _reconcile(self, container_ids: list[str]) -> None:
        """Resolve the death of watched containers that stopped while we were not listening."""
        api = await self._connect()
        for container_id in container_ids:
            try:
                info = await self._call(api.inspect_container, container_id)
            except docker.errors.NotFound:
                self._on_death(container_id, None)
                continue
            except (docker.errors.APIError, RuntimeFailure) as exc:
                logger.warning("cannot check container %s: %s", container_id[:12], exc)
                continue
            if not info.get("State", {}).get("Running"):
                self._on_death(container_id, info.get("State", {}).get("ExitCode"))

    async def _supervise(self, rec: _Container, exited: asyncio.Future[int | None]) -> None:
        """Restart a container that crashes, with backoff, until the policy gives up."""
        state = rec.state
        container_id = rec.container_id
        if container_id is None:
            return
        api = await self._connect()
        code = await asyncio.shield(exited)
        while True:
            state.exit_code = code
            if code == 0:
                state.status = Status.EXITED
                self._notify(state)
                return
            who = f"component {state.skill}/{state.component}"
            # docker-init runs the command, so a missing one only shows as exit 127.
            message = unrunnable(code, who, rec.command)
            delay = None if message else rec.budget.next_delay(time.monotonic())
            if delay is None:
                message = message or give_up_message(who, rec.budget.policy, code)
                logger.warning("%s", message)
                state.status = Status.FAILED
                state.message = message
                self._notify(state)
                return
            state.status = Status.RESTARTING
            self._notify(state)
            await asyncio.sleep(delay)
            async with rec.lock:
                exited = self._expect_death(container_id)
                try:
                    await self._call(api.start, container_id)
                except (docker.errors.APIError, RuntimeFailure) as exc:
                    self._waiters.pop(container_id, None)
                    logger.warning("cannot restart %s: %s", who, exc)
                    state.message = f"{who}: cannot restart its container: {exc}"
                    code = None
                    continue
            state.restarts += 1
            state.status = Status.RUNNING
            state.exit_code = None
            state.message = None
            state.started_at = time.time()
            self._notify(state)
            code = await asyncio.shield(exited)


def _policy_from_label(text: str | None) -> RestartPolicy:
    """Read the restart policy a container was created with."""
    if not text:
        return RestartPolicy()
    try:
        return RestartPolicy(**json.loads(text))
    except (TypeError, ValueError):
        return RestartPolicy()


async def _get_json(socket_path: str, url: str, timeout: float = 10.0) -> Any:
    """GET a Docker API URL over its unix socket; HTTP/1.0, so the answer simply ends at EOF."""
    async with asyncio.timeout(timeout):
        reader, writer = await asyncio.open_unix_connection(socket_path)
        try:
            writer.write(f"GET {url} HTTP/1.0\r\nHost: docker\r\n\r\n".encode())
            data = await reader.read()
        finally:
            writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    status = head.split(b"\r\n", 1)[0].decode("latin-1")
    if status.split(" ")[1:2] != ["200"]:
        raise RuntimeFailure(f"Docker answered {status!r} to GET {url}")
    return json.loads(body)


def _sample_stats(api: APIClient, container_id: str) -> tuple[dict[str, Any], float]:
    """Take one stats sample without Docker's one-second second sample."""
    raw = api.stats(container_id, stream=False, one_shot=True)
    return raw, time.time()


def _usage(raw: Mapping[str, Any]) -> tuple[Usage, float]:
    """Turn a Docker stats sample into usage and the container's total CPU seconds."""
    cpu_seconds = ((raw.get("cpu_stats") or {}).get("cpu_usage") or {}).get("total_usage", 0) / 1e9
    memory = raw.get("memory_stats") or {}
    detail = memory.get("stats") or {}
    # What `docker stats` shows: usage minus the page cache the kernel can drop.
    cache = detail.get("inactive_file", detail.get("total_inactive_file", detail.get("cache", 0)))
    ram = max(memory.get("usage", 0) - cache, 0) / MIB
    networks = (raw.get("networks") or {}).values()
    io_read = io_write = 0
    for entry in (raw.get("blkio_stats") or {}).get("io_service_bytes_recursive") or ():
        op = str(entry.get("op", "")).lower()
        if op == "read":
            io_read += entry.get("value", 0)
        elif op == "write":
            io_write += entry.get("value", 0)
    usage = Usage(
        ram=ram,
        net_rx=sum(n.get("rx_bytes", 0) for n in networks),
        net_tx=sum(n.get("tx_bytes", 0) for n in networks),
        io_read=io_read,
        io_write=io_write,
    )
    return usage, cpu_seconds
