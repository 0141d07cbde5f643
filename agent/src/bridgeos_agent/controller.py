"""The Robot Controller (thesis §3.3): the robot's link to the cloud and the owner of its Skills.

One asyncio task tree per robot: the cloud session (``session``: connection, outbox,
retransmission), the resource monitor, the cloud role takeover watch (``cloudrole``,
Algorithm 7), volume sync, and one supervisor per active Skill. Components are placed by
``placement`` (Algorithm 1); the cloud's commands are answered by ``handlers``. This module
keeps the life cycle and the wiring between them.
"""

from __future__ import annotations

import asyncio
import dataclasses
import functools
import importlib.util
import logging
import os
import time
from collections.abc import Callable, Coroutine, Iterable, Mapping
from pathlib import Path
from typing import Any

from bridgeos_agent import handlers
from bridgeos_agent.agentsettings import AgentSettings
from bridgeos_agent.bridges.graph import BridgeError, BridgeGraph
from bridgeos_agent.bridges.recorder import Recordings
from bridgeos_agent.bridges.relay import BridgeRelay
from bridgeos_agent.cloudrole import CloudRole
from bridgeos_agent.delivery import DeliveryRates
from bridgeos_agent.handover import hand_over
from bridgeos_agent.logonce import LogOnce
from bridgeos_agent.logs.service import ComponentLogService
from bridgeos_agent.metrics import AgentMetrics
from bridgeos_agent.monitor import RESOURCES, Reporter, ResourceMonitor, SimulatedRobot, SystemRobot
from bridgeos_agent.network import CloudNetwork
from bridgeos_agent.outbox import Outbox
from bridgeos_agent.placement import Placement
from bridgeos_agent.protocol import MAX_METRICS_PER_FRAME, Envelope, Event, ProtocolError
from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import SkillStatusName as SS
from bridgeos_agent.robotconfig import RobotConfig
from bridgeos_agent.ros2graph import Ros2Graph
from bridgeos_agent.rosmaster import find_ros_master
from bridgeos_agent.runtime import ComponentSpec, Runtime, Usage, create_runtime
from bridgeos_agent.runtime.usage import MIB
from bridgeos_agent.session import AuthenticationRefused, Session
from bridgeos_agent.skillconfig import SkillConfig, parse_skill_config
from bridgeos_agent.state import SkillRecord, StateFile, find_skill, previous_placement
from bridgeos_agent.supervisor import SkillPlugin, SkillSupervisor
from bridgeos_agent.tasks import TaskOwner
from bridgeos_agent.tokenfile import write_token_file
from bridgeos_agent.volumesync import VolumeSync

__all__ = ["AgentSettings", "AuthenticationRefused", "RobotController", "SkillRecord", "previous_placement"]

logger = logging.getLogger("bridgeos_agent")


class RobotController:
    """Attach one robot to the cloud and run its Skills (it is the ``SkillHost`` of their plug-ins)."""

    def __init__(
        self,
        settings: AgentSettings,
        *,
        runtime: Runtime | None = None,
        plugins: Mapping[str, SkillPlugin] | None = None,
        say: Callable[[str], None] | None = None,
    ) -> None:
        self.settings = settings
        self.data_dir = Path(settings.data_dir)
        self.data_dir.mkdir(parents=True, exist_ok=True)
        self.say: Callable[[str], None] = say or (lambda line: logger.info("%s", line))
        self.placement = Placement(self)
        self.cloud_role = CloudRole(self)
        self.outbox = Outbox(
            self.data_dir / "outbox.sqlite3",
            max_bytes=settings.outbox_max_bytes,
            memory_bytes=settings.outbox_memory_bytes,
        )
        self.metrics = AgentMetrics(settings.robot)  # what --metrics serves (bridgeos_agent.metrics)
        options = dict(settings.runtime_options)
        if settings.runtime == "docker":
            from bridgeos_agent.runtime.images import RegistryLogin

            # Images the robot lacks come from its cloud's registry, with tokens only its cloud grants.
            login = RegistryLogin.for_cloud(settings.master, settings.robot, settings.token, settings.ca_file)
            options.setdefault("registry", login)
        self.runtime: Runtime = runtime or create_runtime(
            settings.runtime,
            settings.robot,
            data_dir=self.data_dir / "runtime",
            on_status=self.placement.on_runtime_status,
            **options,
        )
        if runtime is not None and runtime.on_status is None:
            runtime.on_status = self.placement.on_runtime_status
        if hasattr(self.runtime, "on_pull"):  # a runtime that pulls images reports their progress
            self.runtime.on_pull = self.placement.pull_progress
        if hasattr(self.runtime, "images"):  # and keeps every image a Skill of the robot names
            self.runtime.images.in_use = self._images_in_use
        if plugins is None:
            from bridgeos_agent.manager import skill_manager_plugin
            from bridgeos_agent.router import skill_router_plugin

            plugins = {"manager": skill_manager_plugin, "router": skill_router_plugin}
        self.plugins = dict(plugins)
        self.config: RobotConfig | None = None
        self.config_from_cloud = asyncio.Event()
        self.skills: dict[str, SkillRecord] = {}
        self.ros_master: str | None = None  # the master components use
        self.ros2_graph: Ros2Graph | None = None  # the robot's ROS 2 graph, when the agent routes ROS 2
        self.ros2_discovery_server: str | None = None  # "host:port" the cloud runs for the robot's cloud graph
        self.cloud_relays: dict[str, Any] = {}  # Skill id -> CloudRelayInfo the cloud named (cloud-side routing)
        self.stopped = asyncio.Event()
        self.exit_code = 0
        self.usage: dict[tuple[str, str], Usage] = {}  # the runtime's last measurement per (skill, component)
        self.tasks = TaskOwner()  # commands being handled and other background work
        self._loops: list[asyncio.Task[Any]] = []
        self._reporter = Reporter(max_interval=settings.report_max_interval)
        self._delivery = DeliveryRates()  # what each Skill Router delivered and dropped, per second
        self._stats_failures = LogOnce(logger, "measuring the components' usage")
        self.state = StateFile(self.data_dir / "state.json", self._collect_state)
        self.volumes = VolumeSync(self)
        self.recordings = Recordings(self)  # MCAP recordings of the robot's topics (bridges.recorder)
        self.network = CloudNetwork(
            master=settings.master,
            robot=settings.robot,
            token=settings.token,
            data_dir=self.data_dir,
            say=self.say,
            ca_file=settings.ca_file,
            allow_insecure=settings.allow_insecure,
            vpn_device=settings.vpn_device,
            openvpn=settings.openvpn,
            firewall_mode=settings.firewall,
        )
        self.session = Session(
            settings,
            self.network,
            self.outbox,
            self.tasks,
            say=self.say,
            handle=functools.partial(handlers.dispatch, self),
            timing=self._link_timing,
            on_authenticated=self._on_authenticated,
            on_contact=self.cloud_role.contact,
            on_refused=self.placement.on_refused,
            stop=self.stop,
            stopped=self.stopped,
            on_disconnect=self._on_disconnect,
        )
        self.connected = self.session.connected
        # Every component's stdout and stderr: kept in rings on disk, shipped when the link is idle.
        self.logs = ComponentLogService(self.data_dir / "logs", self.runtime, self.session)
        # The cloud's rosbridge/Foxglove clients of this robot, relayed over the link (bridges.relay).
        self.bridges = BridgeRelay(self.emit, self._bridge_graph, send_binary=self.session.send_raw)
        robot = (settings.simulated or SimulatedRobot()) if settings.simulate else SystemRobot()
        self.monitor = ResourceMonitor(robot)

    # ------------------------------------------------------------------ life cycle

    async def run(self) -> int:
        """Run until stopped (signal, shutdown command or a refused token); return the exit code."""
        await self._restore()
        await self.recordings.recover()  # recordings a killed run left open: cut short, their chunks kept
        if self.settings.detect_ros_master:
            self.local_ros_master = self.ros_master = await asyncio.to_thread(find_ros_master)
        self.say(f"ROS master: {self.ros_master or 'none found here; asking the cloud for one'}")
        self.ros2_graph = self._detect_ros2()
        self.session.local_ros2 = self.ros2_graph.as_dict() if self.ros2_graph is not None else None
        loop = asyncio.get_running_loop()
        self.cloud_role.start(self._link_timing()[1])
        for coroutine, name in (
            (self.session.run(), "connection"),
            (self.session.resend_loop(), "resend"),
            (self._monitor_loop(), "monitor"),
            (self.cloud_role.run(), "takeover"),
            (self._startup(), "startup"),
            (self.volumes.run(), "volumes"),
            (self.logs.run(), "logs"),
        ):
            self._loops.append(loop.create_task(coroutine, name=name))
        await self.stopped.wait()
        await self._shutdown()
        return self.exit_code

    def stop(self, code: int = 0) -> None:
        """Ask the controller to stop (safe to call from a signal handler)."""
        self.exit_code = self.exit_code or code
        self.stopped.set()

    async def _shutdown(self) -> None:
        self.say("stopping")
        # Before the link's loops go: a recording's last chunks reach the outbox, sent on the next run.
        await self.recordings.close()
        for task in self._loops:
            task.cancel()
        await asyncio.gather(*self._loops, return_exceptions=True)
        await self.tasks.close()
        await self.bridges.shutdown()
        for record in self.skills.values():
            if record.supervisor is not None:
                await record.supervisor.close()
        self.state.save_now()
        await self.network.close()
        # By default components keep running across an agent restart; the next agent re-adopts them.
        await self.runtime.close(stop_components=self.settings.stop_components_on_exit)
        if self.session.ws is not None:
            await self.session.close_socket(self.session.ws)
        self.outbox.close()
        self.say("stopped")

    async def _restore(self) -> None:
        """Load the last config and Skills and re-adopt the components still running."""
        saved = self.state.load(self.say)
        if saved is None:
            return
        if saved.config is not None:
            self.config = saved.config
            # The CA the cloud pinned, and its tunnel, serve from the first connection on.
            self.network.apply_config(saved.config)
            self.logs.apply(saved.config.logs)
        self.skills.update(saved.skills)
        adopted = await self.runtime.load_state(saved.runtime)
        for component in adopted:
            record = self.skills.get(component.skill)
            if record is not None and component.component in record.config.components:
                record.locations[component.component] = "robot"
                record.statuses[component.component] = CS.RUNNING
        if adopted:
            self.say(f"re-adopted {len(adopted)} running component(s)")

    def _collect_state(self) -> dict[str, Any]:
        return {
            "config": self.config.model_dump(mode="json") if self.config else None,
            "skills": {skill_id: record.to_dict() for skill_id, record in self.skills.items()},
            "runtime": self.runtime.get_state(),
        }

    def save_soon(self) -> None:
        """Save the state within 0.2 s."""
        self.state.save_soon()

    # ------------------------------------------------------------------ the cloud link

    @property
    def local_ros_master(self) -> str | None:
        """Return the ROS master found on the robot, if any (told to the cloud when connecting)."""
        return self.session.local_ros_master

    @local_ros_master.setter
    def local_ros_master(self, value: str | None) -> None:
        self.session.local_ros_master = value

    @property
    def metric_points_sent(self) -> int:
        """Return how many metric points the robot has sent to the cloud."""
        return self.session.metric_points_sent

    @property
    def cloud_bytes(self) -> list[int]:
        """Return the bytes received from and sent to the cloud."""
        return self.session.cloud_bytes

    def _link_timing(self) -> tuple[float, float]:
        """Return the keepalive interval and after how long a silent cloud counts as lost."""
        if self.config is None:
            return 5.0, 15.0
        return self.config.heartbeat_interval, self.config.connection_lost_after

    def link_latency(self) -> float:
        """Return the cloud link's round trip in seconds, as its keepalive measured it (0 if unknown)."""
        ws = self.session.ws
        return float(getattr(ws, "latency", 0.0) or 0.0) if ws is not None else 0.0

    def _detect_ros2(self) -> Ros2Graph | None:
        """Return the ROS 2 graph this agent routes in, or None (saying why) when ROS 2 routing is off."""
        mode = self.settings.ros2
        if mode == "off" or (mode == "auto" and self.settings.simulate):
            return None
        if importlib.util.find_spec("rclpy") is None:
            self.say("ROS 2: rclpy is not installed here, so ROS 2 routing is off (pip install 'bridgeos-agent[ros2]')")
            return None
        try:
            graph = Ros2Graph.from_env()
        except ValueError as exc:
            self.say(f"ROS 2: routing is off, the ROS 2 environment is not usable ({exc})")
            return None
        self.say(f"ROS 2: domain {graph.domain_id}, {graph.rmw}, discovery {graph.discovery_range}")
        return graph

    def _on_authenticated(self, success: Any) -> None:
        """Count the new connection, then take the ROS master and ROS 2 discovery server the cloud named."""
        self.metrics.connected()
        self._use_ros_master(getattr(success, "ros_master", None))
        self.cloud_relays = dict(getattr(success, "cloud_relays", None) or {})
        server = getattr(success, "ros2_discovery_server", None)
        if self.ros2_graph is not None and server != self.ros2_discovery_server:
            self.ros2_discovery_server = server
            if server:
                self.say(f"ROS 2: the robot's cloud graph is found through the discovery server {server}")

    def _on_disconnect(self) -> None:
        """End the bridge sessions: their clients were on the link that dropped."""
        self.bridges.forget_blobs()  # now, not when the task runs: the next link may come first
        self.logs.shipper.on_disconnect()
        self.spawn(self.bridges.close_sessions())

    async def _bridge_graph(self) -> BridgeGraph:
        """Join the robot's graph for the bridges: its ROS master's (ROS 1), else its ROS 2 graph."""
        if self.ros_master:
            from bridgeos_agent.bridges.ros1graph import Ros1Graph

            host = os.environ.get("ROS_IP") or os.environ.get("ROS_HOSTNAME") or "127.0.0.1"
            graph = Ros1Graph(self.ros_master, name="/bridgeos_cloud_bridge", host=host)
            await graph.start()
            return graph
        if self.ros2_graph is not None:
            from bridgeos_agent.bridges.ros2graph import Ros2BridgeGraph

            return Ros2BridgeGraph(self.ros2_graph, asyncio.get_running_loop(), name="bridgeos_cloud_bridge")
        raise BridgeError("this robot has no ROS graph: no ROS master was found and ROS 2 routing is off")

    def _use_ros_master(self, offered: str | None) -> None:
        """Take the ROS master the cloud named for this robot (ours, or one it runs)."""
        if offered and offered != self.ros_master:
            self.ros_master = offered
            self.say(f"ROS master: using {offered} from the cloud")
        elif not offered and not self.ros_master:
            self.say("no ROS master here and none from the cloud: ROS routing is off until one is available")

    async def rekey(self, token: str) -> None:
        """Take the new token the cloud gave this robot: kept in the token file first, then used for every login.

        ProtocolError when the token file cannot be written: the new token is used all the same (the old
        one stops working when its grace ends), and the cloud hears that it was not kept.
        """
        unkept: OSError | None = None
        if self.settings.token_file is not None:
            try:
                # Before it is acked: an agent restarted from here on finds the token that works.
                await asyncio.to_thread(write_token_file, self.settings.token_file, token)
            except OSError as exc:
                unkept = exc
        self.settings.token = token
        self.network.token = token  # its VPN profile requests
        images = getattr(self.runtime, "images", None)
        if images is not None and images.login is not None:
            images.login = dataclasses.replace(images.login, token=token)  # its registry token requests
        self.say("re-keyed: the cloud gave this robot a new token")
        if unkept is not None:
            message = (
                f"the new token is in use but could not be kept in {self.settings.token_file}: "
                f"{unkept.strerror or unkept}; a restarted agent will not have it"
            )
            logger.warning("%s", message)
            raise ProtocolError(message, code="token_not_kept")
        if self.settings.token_file is None:
            logger.warning("the new token is kept in memory only: restarted, this agent needs it (see --token-file)")

    async def emit(self, event: Event, data: Mapping[str, Any], *, reply_to: str | None = None) -> Envelope:
        """Send a frame to the cloud; one that changes state is kept on disk until acked."""
        return await self.session.emit(event, data, reply_to=reply_to)

    async def request(self, event: Event, data: Mapping[str, Any], timeout: float = 10.0) -> Envelope | None:
        """Ask the cloud something and wait for the answer (None if it does not come)."""
        return await self.session.request(event, data, timeout)

    def spawn(self, coroutine: Coroutine[Any, Any, Any]) -> None:
        """Run a coroutine in the background, owned until it ends or the agent stops."""
        self.tasks.spawn(coroutine)

    # ------------------------------------------------------------------ config

    def apply_config(self, config: RobotConfig, *, source: str) -> None:
        """Make a validated robot config the one in force and keep it on disk."""
        first = not self.config_from_cloud.is_set()
        self.config = config
        self.cloud_role.set_lost_after(config.connection_lost_after)
        for name in RESOURCES:
            setattr(self.monitor.robot, name, getattr(config.resources, name))
        if source == "cloud":
            self.config_from_cloud.set()
        self.network.apply_config(config)
        self.logs.apply(config.logs)
        images = getattr(self.runtime, "images", None)
        if images is not None:
            images.keep = config.images.keep_per_repository
            images.disk_reserve = int(config.images.disk_reserve_mb * MIB)
        use_subnet = getattr(self.runtime, "use_subnet", None)
        if config.subnets is not None and use_subnet is not None:
            use_subnet(config.subnets.local)
        self.save_soon()
        if first and source == "cloud":
            self.say(f"robot config received (heuristic {config.heuristic}, offloading {config.offloading})")

    # ------------------------------------------------------------------ Skills

    def _images_in_use(self) -> set[str]:
        """Return the images the robot's Skills run on the robot (kept when unused images are removed)."""
        return {
            component.robot.image
            for record in self.skills.values()
            for component in record.config.components.values()
            if component.robot is not None and component.robot.image
        }

    async def _startup(self) -> None:
        """Once the cloud sent a config, relaunch the Skills that ran before, in parallel."""
        await self.config_from_cloud.wait()
        wanted = [skill for skill, record in self.skills.items() if record.status in (SS.RUNNING, SS.STARTING)]
        if not wanted:
            return
        self.say(f"restarting {len(wanted)} skill(s) with their latest config from the cloud")
        limit = asyncio.Semaphore(self.settings.startup_parallelism)

        async def one(skill_id: str) -> None:
            async with limit:
                reply = await self.request(Event.SKILL_CONFIG_GET, {"skill": skill_id})
                if reply is None or reply.event != Event.SKILL_CONFIG:
                    self.say(f"skill {skill_id}: the cloud has no config for it any more; not restarted")
                    record = self.skills.pop(skill_id)
                    await self.placement.stop_components(record, list(record.config.components))
                    return
                await self.start_skill(parse_skill_config(dict(reply.data["config"])))

        results = await asyncio.gather(*(one(skill_id) for skill_id in wanted), return_exceptions=True)
        for skill_id, result in zip(wanted, results, strict=True):
            if isinstance(result, Exception):
                self.say(f"skill {skill_id}: not restarted: {result}")

    async def start_skill(self, config: SkillConfig, *, starting: Iterable[str] | None = None) -> SkillRecord:
        """Launch a Skill: place each component (Algorithm 1) and start it where it goes."""
        record = self.skills.get(config.skill_id)
        if record is not None and record.status == SS.RUNNING and config.update.strategy == "beside":
            if record.config != config and starting is None:
                return await hand_over(self, record, config)
        if record is None:
            record = self.skills[config.skill_id] = SkillRecord(config=config)
        else:
            record.config = config
        for component in config.components:
            record.locations.setdefault(component, None)
        await self.set_skill_status(record, SS.STARTING)
        if record.supervisor is None:
            record.supervisor = SkillSupervisor(
                config.skill_id, on_failure=functools.partial(self._plugin_failed, record)
            )
            # The plug-ins' view of the robot is the SkillHost protocol (hosts.py).
            record.supervisor.context["controller"] = self
            for name, plugin in self.plugins.items():
                record.supervisor.start(name, plugin)
            # The manager's Components API must listen before components get its URL.
            late = await record.supervisor.wait_ready(timeout=10.0)
            if late:
                self.say(f"skill {config.skill_id}: {', '.join(late)} not ready after 10 s; starting anyway")
        names = list(starting if starting is not None else config.components)
        results = await asyncio.gather(
            *(self.placement.place_component(record, name) for name in names), return_exceptions=True
        )
        failures = [
            f"{name}: {result}" for name, result in zip(names, results, strict=True) if isinstance(result, Exception)
        ]
        if failures and len(failures) == len(names):
            await self.set_skill_status(record, SS.FAILED, "; ".join(failures)[:1900])
        else:
            await self.set_skill_status(record, SS.RUNNING, "; ".join(failures)[:1900] or None)
        return record

    async def stop_skill(self, skill_id: str) -> None:
        """Stop a Skill's components on the robot and in the cloud."""
        record = find_skill(self.skills, skill_id)
        await self.set_skill_status(record, SS.STOPPING)
        await self.placement.stop_components(record, list(record.config.components))
        if record.supervisor is not None:
            await record.supervisor.close()
            record.supervisor = None
        await self.set_skill_status(record, SS.STOPPED)

    async def set_skill_status(self, record: SkillRecord, status: SS, message: str | None = None) -> None:
        record.status = status
        data: dict[str, Any] = {"skill": record.config.skill_id, "status": str(status)}
        if message:
            data["message"] = message
        await self.emit(Event.SKILL_STATUS, data)
        self.save_soon()

    def _plugin_failed(self, record: SkillRecord, name: str, message: str) -> None:
        self.spawn(self.set_skill_status(record, SS.FAILED, message))

    # ------------------------------------------------------------------ components (placement's doors)

    async def place_component(self, record: SkillRecord, name: str, *, location: str | None = None) -> str:
        """Start a component where it should run; return that location."""
        return await self.placement.place_component(record, name, location=location)

    async def migrate_component(self, record: SkillRecord, name: str, target: str | None) -> str:
        """Move a running component to the other side: start there first, then stop here."""
        return await self.placement.migrate_component(record, name, target)

    def component_spec(self, record: SkillRecord, name: str) -> ComponentSpec:
        """Build the launch spec of a robot-side component with the env contract."""
        return self.placement.component_spec(record, name)

    def forget_component(self, skill_id: str, name: str) -> None:
        """Drop what was measured of a component that stopped."""
        self._reporter.forget(skill_id, name)
        self.usage.pop((skill_id, name), None)

    def takeover_components(self) -> dict[str, list[str]]:
        """Return the cloud components running on the robot because the cloud is lost."""
        return self.cloud_role.components()

    # ------------------------------------------------------------------ monitoring

    async def _monitor_loop(self) -> None:
        """Sample the robot and its components; send what changed enough, or is due."""
        interval = self.settings.sample_interval
        stats_every = max(1, round(5.0 / interval)) if self.runtime.name == "docker" else 1
        tick = 0
        last_cloud = (0, 0, time.monotonic())
        # Points selected since the last metrics frame, sent together every report interval.
        unsent: list[dict[str, object]] = []
        last_report = time.monotonic()
        while True:
            await asyncio.sleep(interval)
            tick += 1
            if tick % stats_every == 0:
                await self._measure_components()
            now = time.monotonic()
            cloud_bytes = self.session.cloud_bytes
            span = max(1e-3, now - last_cloud[2])
            cloud_rates = ((cloud_bytes[0] - last_cloud[0]) / span, (cloud_bytes[1] - last_cloud[1]) / span)
            last_cloud = (cloud_bytes[0], cloud_bytes[1], now)
            sample = self.monitor.sample(self.placement.reserved(), cloud_rates)
            readings: list[tuple[str, float, str | None, str | None]] = [
                (name, float(value), None, None) for name, value in sample.values.items()
            ]
            for (skill, component), usage in self.usage.items():
                readings.append(("cpu", round(100 * usage.cpu, 2), skill, component))
                readings.append(("ram", round(usage.ram, 1), skill, component))
            routers = ((skill_id, record.context("router")) for skill_id, record in list(self.skills.items()))
            readings += self._delivery.sample(((s, r) for s, r in routers if r is not None), now)
            unsent += self._reporter.select(time.time(), readings)
            # Half a sample early counts as due: sleeps run late, and a frame must not slip a whole sample.
            due = now - last_report >= self.settings.report_interval - interval / 2
            if unsent and (due or len(unsent) >= MAX_METRICS_PER_FRAME // 2):
                last_report = now
                points, unsent = unsent, []
                await self.emit(Event.METRICS, {"metrics": points})

    async def _measure_components(self) -> None:
        """Take the runtime's measurement of every component; keep the last one if it fails."""
        try:
            self.usage = await self.runtime.stats()
        except Exception as exc:
            # A runtime backend can fail in its own ways (docker API, /proc races); said once per distinct error.
            self._stats_failures.failed(exc)
        else:
            self._stats_failures.worked()
