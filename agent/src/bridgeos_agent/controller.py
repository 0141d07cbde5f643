"""The Robot Controller (thesis §3.3): the robot's link to the cloud and the owner of its Skills.

One asyncio task tree per robot: the cloud connection (reconnecting with backoff), the
outbox that keeps every owed frame on disk until acked, the resource monitor, the cloud
role takeover watch (Algorithm 7), and one supervisor per active Skill. Components are
launched through a runtime after an allocation check (Algorithm 1); cloud-side launches
are forwarded to the cloud.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import json
import logging
import os
import ssl
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import websockets
import websockets.asyncio.client
from pydantic import ValidationError
from websockets.client import backoff

from bridgeos_agent import protocol
from bridgeos_agent.allocation import (
    AllocationSettings,
    Cloud,
    Decision,
    Measurement,
    Refuse,
    Replace,
    allocate,
    allocation_state,
)
from bridgeos_agent.errors import field_errors
from bridgeos_agent.heuristics import Resources, Weights
from bridgeos_agent.metrics import AgentMetrics
from bridgeos_agent.monitor import Reporter, ResourceMonitor, SimulatedRobot, SystemRobot
from bridgeos_agent.network import VPN, CloudNetwork, Target
from bridgeos_agent.outbox import Outbox
from bridgeos_agent.protocol import ComponentStatusName as CS
from bridgeos_agent.protocol import Envelope, Event, ProtocolError
from bridgeos_agent.protocol import SkillStatusName as SS
from bridgeos_agent.robotconfig import RobotConfig, merge_config_changes, parse_robot_config
from bridgeos_agent.rosmaster import find_ros_master
from bridgeos_agent.rosnames import instance_namespace
from bridgeos_agent.runtime import ComponentSpec, ComponentState, Runtime, RuntimeFailure, Status, create_runtime
from bridgeos_agent.skillconfig import SkillConfig, parse_skill_config
from bridgeos_agent.supervisor import SkillPlugin, SkillSupervisor
from bridgeos_agent.takeover import CloudMonitor, plan_takeover
from bridgeos_agent.volumesync import VolumeSync

__all__ = ["AgentSettings", "AuthenticationRefused", "RobotController"]

logger = logging.getLogger("bridgeos_agent")

# Error codes from the cloud that mean "try again later": the frame stays owed.
RETRY_CODES = frozenset({"unavailable", "internal_error", "rate_limited"})


class AuthenticationRefused(RuntimeError):
    """The cloud refused the robot's id or token: retrying will not help."""


@dataclass
class AgentSettings:
    """Everything `bridgeos-agent run` is told."""

    master: str
    robot: str
    token: str
    data_dir: Path
    runtime: str = "process"
    simulate: bool = False
    sample_interval: float = 1.0
    report_max_interval: float = 10.0
    startup_parallelism: int = 8
    outbox_max_bytes: int = 64 * 1024 * 1024
    reconnect_initial: float = 1.0
    reconnect_max: float = 30.0
    runtime_options: dict[str, Any] = field(default_factory=dict)
    detect_ros_master: bool = True
    stop_components_on_exit: bool = False
    simulated: SimulatedRobot | None = None
    # How long a move to the cloud waits for the cloud to report its copy running.
    cloud_start_timeout: float = 90.0
    # How often Skill volumes are scanned for changes to send to the cloud (0: never).
    volume_sync_interval: float = 1.0
    ca_file: Path | None = None  # the CA that signs the cloud's TLS certificate (else pinned, else the system's)
    allow_insecure: bool = False  # plain ws:// to another machine
    vpn_device: str = "bridgeos-vpn"
    openvpn: str = "openvpn"
    firewall: str = "auto"  # auto (apply when root, else print) | apply | print | off


@dataclass
class SkillRecord:
    """What the controller knows of one Skill on this robot."""

    config: SkillConfig
    status: SS = SS.STOPPED
    locations: dict[str, str | None] = field(default_factory=dict)  # component -> robot|cloud|None
    statuses: dict[str, CS] = field(default_factory=dict)
    supervisor: SkillSupervisor | None = None
    # What the cloud reported of each cloud copy: {"runtime", "id", "address", "ports": {"<port>": <port>}}.
    cloud_containers: dict[str, dict[str, Any]] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        """Return what survives an agent restart."""
        return {
            "config": self.config.model_dump(mode="json"),
            "status": str(self.status),
            "locations": self.locations,
        }


class RobotController:
    """Attach one robot to the cloud and run its Skills."""

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
        self.say = say or (lambda line: logger.info("%s", line))
        self.outbox = Outbox(self.data_dir / "outbox.sqlite3", max_bytes=settings.outbox_max_bytes)
        self.metrics = AgentMetrics(settings.robot)  # what --metrics serves (bridgeos_agent.metrics)
        self.runtime = runtime or create_runtime(
            settings.runtime,
            settings.robot,
            data_dir=self.data_dir / "runtime",
            on_status=self._on_runtime_status,
            **settings.runtime_options,
        )
        if runtime is not None and runtime.on_status is None:
            runtime.on_status = self._on_runtime_status
        if plugins is None:
            from bridgeos_agent.manager import skill_manager_plugin
            from bridgeos_agent.router import skill_router_plugin

            plugins = {"manager": skill_manager_plugin, "router": skill_router_plugin}
        self.plugins = dict(plugins)
        self.config: RobotConfig | None = None
        self.config_from_cloud = asyncio.Event()
        self.skills: dict[str, SkillRecord] = {}
        self.ros_master: str | None = None  # the master components use
        self.local_ros_master: str | None = None  # the master found on the robot, if any
        self.connected = asyncio.Event()
        self.stopped = asyncio.Event()
        self.exit_code = 0
        self.ws: Any = None
        self.cloud_bytes = [0, 0]  # received, sent on the cloud link
        self.metric_points_sent = 0
        self._unacked: dict[str, tuple[float, int]] = {}  # frame id -> (next resend at, attempts)
        self._replaying = False
        self._dedup = protocol.Dedup(capacity=2000)
        self._answers: dict[str, str] = {}  # command id -> the frame that answered it
        self._handling: set[str] = set()  # ids of frames whose handler has not answered yet
        self._waiters: dict[str, asyncio.Future[Envelope]] = {}
        self._tasks: list[asyncio.Task] = []
        self._handlers: set[asyncio.Task] = set()
        self._takeover: dict[str, list[str]] = {}
        self._usage: dict[tuple[str, str], Any] = {}
        self._reporter = Reporter(max_interval=settings.report_max_interval)
        self._save_pending = False
        self._cloud_monitor: CloudMonitor | None = None
        self._startup_done = False
        self._lock = asyncio.Lock()  # serialises placement decisions so two never claim the same headroom
        self._cloud_waiters: dict[tuple[str, str], asyncio.Future[tuple[str, str | None]]] = {}
        self.volumes = VolumeSync(self)
        self._tls_failure: str | None = None
        self._holding = False  # moving to another path: new frames wait in the outbox
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
        if settings.simulate:
            self.monitor = ResourceMonitor(settings.simulated or SimulatedRobot())
        else:
            self.monitor = ResourceMonitor(SystemRobot())

    # ------------------------------------------------------------------ life cycle

    async def run(self) -> int:
        """Run until stopped (signal, shutdown command or a refused token); return the exit code."""
        await self._restore()
        if self.settings.detect_ros_master:
            self.local_ros_master = self.ros_master = await asyncio.to_thread(find_ros_master)
        self.say(f"ROS master: {self.ros_master or 'none found here; asking the cloud for one'}")
        loop = asyncio.get_running_loop()
        self._cloud_monitor = CloudMonitor(self._lost_after(), time.monotonic())
        for coroutine, name in (
            (self._connection_loop(), "connection"),
            (self._resend_loop(), "resend"),
            (self._monitor_loop(), "monitor"),
            (self._takeover_loop(), "takeover"),
            (self._startup(), "startup"),
            (self.volumes.run(), "volumes"),
        ):
            self._tasks.append(loop.create_task(coroutine, name=name))
        await self.stopped.wait()
        await self._shutdown()
        return self.exit_code

    def stop(self, code: int = 0) -> None:
        """Ask the controller to stop (safe to call from a signal handler)."""
        self.exit_code = self.exit_code or code
        self.stopped.set()

    async def _shutdown(self) -> None:
        self.say("stopping")
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for task in list(self._handlers):
            task.cancel()
        await asyncio.gather(*self._handlers, return_exceptions=True)
        for record in self.skills.values():
            if record.supervisor is not None:
                await record.supervisor.close()
        self._save_now()
        await self.network.close()
        # By default components keep running across an agent restart; the next agent re-adopts them.
        await self.runtime.close(stop_components=self.settings.stop_components_on_exit)
        if self.ws is not None:
            with contextlib.suppress(Exception):
                await self.ws.close()
        self.outbox.close()
        self.say("stopped")

    # ------------------------------------------------------------------ persistence

    @property
    def _state_path(self) -> Path:
        return self.data_dir / "state.json"

    async def _restore(self) -> None:
        """Load the last config and Skills and re-adopt the components still running."""
        try:
            state = json.loads(self._state_path.read_text())
        except FileNotFoundError:
            return
        except (OSError, ValueError) as exc:
            self.say(f"ignoring unreadable state file {self._state_path}: {exc}")
            return
        if state.get("config"):
            with contextlib.suppress(ValueError):
                self.config = parse_robot_config(state["config"])
                # The CA the cloud pinned, and its tunnel, serve from the first connection on.
                self.network.apply_config(self.config)
        for skill_id, saved in state.get("skills", {}).items():
            try:
                config = parse_skill_config(saved["config"])
            except (ValueError, KeyError):
                continue
            record = SkillRecord(config=config, status=SS(saved.get("status", "stopped")))
            record.locations = {c: saved.get("locations", {}).get(c) for c in config.components}
            self.skills[skill_id] = record
        adopted = await self.runtime.load_state(state.get("runtime", {}))
        for component in adopted:
            record = self.skills.get(component.skill)
            if record is not None and component.component in record.config.components:
                record.locations[component.component] = "robot"
                record.statuses[component.component] = CS.RUNNING
        if adopted:
            self.say(f"re-adopted {len(adopted)} running component(s)")

    def _save_soon(self) -> None:
        if not self._save_pending:
            self._save_pending = True
            asyncio.get_running_loop().call_later(0.2, self._save_now)

    def _save_now(self) -> None:
        self._save_pending = False
        state = {
            "config": self.config.model_dump(mode="json") if self.config else None,
            "skills": {skill_id: record.to_dict() for skill_id, record in self.skills.items()},
            "runtime": self.runtime.get_state(),
        }
        tmp = self._state_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(state))
        os.replace(tmp, self._state_path)

    # ------------------------------------------------------------------ the cloud link

    def _lost_after(self) -> float:
        return self.config.connection_lost_after if self.config else 15.0

    async def _connection_loop(self) -> None:
        """Stay connected on the path the network prefers (VPN or WSS), moving when the preference changes."""
        while True:
            target = self.network.target()
            connecting = asyncio.ensure_future(self._connect(target))
            switching = asyncio.ensure_future(self.network.wait_change(target.path))
            watchdog = asyncio.ensure_future(self._vpn_watchdog(target))
            try:
                done, _ = await asyncio.wait({connecting, switching}, return_when=asyncio.FIRST_COMPLETED)
                if switching in done and target.path != VPN:
                    # The old path still works: let the cloud ack what is in flight, so nothing is applied twice.
                    await self._drain(timeout=3.0)
            finally:
                for task in (connecting, switching, watchdog):
                    task.cancel()
                await asyncio.gather(connecting, switching, watchdog, return_exceptions=True)
            if connecting in done:
                return  # refused: run() stops

    async def _drain(self, timeout: float) -> None:
        """Hold new frames (the outbox keeps them) until every frame sent on this connection is acked."""
        self._holding = True
        deadline = time.monotonic() + timeout
        # Acks are handled by the reader task; a 20 ms poll for at most `timeout` is simplest.
        while self.ws is not None and self._unacked and time.monotonic() < deadline:  # noqa: ASYNC110
            await asyncio.sleep(0.02)

    async def _vpn_watchdog(self, target: Target) -> None:
        """Fall back to WSS when the cloud does not answer through an up tunnel."""
        if target.path != VPN:
            return
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self.connected.wait(), self.network.vpn_connect_timeout)
            return
        self.network.vpn_unusable()

    async def _connect(self, target: Target) -> None:
        heartbeat = self.config.heartbeat_interval if self.config else 5.0
        delays = functools.partial(
            backoff,
            initial_delay=self.settings.reconnect_initial,
            min_delay=self.settings.reconnect_initial,
            max_delay=self.settings.reconnect_max,
        )
        self.say(f"connecting to {target.url} as robot {self.settings.robot} ({target.path})")
        async for ws in websockets.connect(
            target.url,
            reconnect_delays=delays,
            ping_interval=heartbeat,
            ping_timeout=self._lost_after(),
            max_size=protocol.MAX_FRAME_BYTES * 2,
            open_timeout=10,
            compression=None,
            process_exception=self._connect_failed,
            **target.connect_options(),
        ):
            try:
                await self._session(ws, target.path)
            except AuthenticationRefused as exc:
                self.say(f"the cloud refused this robot: {exc}. Check --robot and --token.")
                self.stop(3)
                return
            except websockets.ConnectionClosed:
                pass
            finally:
                self._on_disconnect()
                if self.stopped.is_set() or asyncio.current_task().cancelling():
                    # Moving to another path (or stopping): close this socket now, not at garbage collection.
                    with contextlib.suppress(Exception):
                        await asyncio.wait_for(ws.close(), 2)

    def _connect_failed(self, exc: Exception) -> Exception | None:
        """Say why a TLS handshake failed (once per reason), then let websockets retry as usual."""
        if isinstance(exc, ssl.SSLError):
            reason = exc.reason or str(exc)
            if isinstance(exc, ssl.SSLCertVerificationError):
                reason = f"certificate verify failed ({exc.verify_message})"
            if reason != self._tls_failure:
                self._tls_failure = reason
                self.say(f"TLS handshake with the cloud failed: {reason}. Check --ca or the cloud's certificate.")
        return websockets.asyncio.client.process_exception(exc)

    async def _session(self, ws: Any, path: str = "direct") -> None:
        credentials: dict[str, Any] = {
            "robot": self.settings.robot,
            "token": self.settings.token,
            "ros_master": self.local_ros_master,
        }
        await ws.send(protocol.encode(protocol.make(Event.AUTHENTICATION_ROBOT, credentials, now=time.time())))
        answer = protocol.decode(await asyncio.wait_for(ws.recv(), 10), direction=protocol.Direction.CLOUD_TO_ROBOT)
        if answer.event != Event.AUTHENTICATION_SUCCESS:
            reason = getattr(protocol.parse_payload(answer), "reason", answer.event)
            raise AuthenticationRefused(reason)
        self._use_ros_master(protocol.parse_payload(answer).ros_master)
        self.ws = ws
        self.network.path = path
        self.connected.set()
        self.metrics.connected()
        self.say(f"connected to the cloud ({'through the VPN' if path == VPN else 'over ' + ws_scheme(ws)})")
        self._contact()
        await self._replay_backlog()
        # Which path this connection takes is a metric of its own ("vpn": 1 through the tunnel, 0 direct).
        await self.emit(Event.METRICS, {"metrics": [self.network.path_point(path)]})
        # The cloud pushes the config on connect; asking as well makes the agent not depend on it.
        await self._send_direct(protocol.make(Event.ROBOT_CONFIG_GET, {}, now=time.time()))
        async for raw in ws:
            self.cloud_bytes[0] += len(raw)
            self._contact()
            try:
                envelope = protocol.decode(raw, direction=protocol.Direction.CLOUD_TO_ROBOT)
            except ProtocolError as exc:
                await self._send_direct(protocol.error_frame(exc, now=time.time()))
                continue
            self._receive(envelope)

    def _use_ros_master(self, offered: str | None) -> None:
        """Take the ROS master the cloud named for this robot (ours, or one it runs)."""
        if offered and offered != self.ros_master:
            self.ros_master = offered
            self.say(f"ROS master: using {offered} from the cloud")
        elif not offered and not self.ros_master:
            self.say("no ROS master here and none from the cloud: ROS routing is off until one is available")

    def _on_disconnect(self) -> None:
        if self.ws is not None:
            self.say("disconnected from the cloud; frames are kept until it is back")
        self.ws = None
        self.network.path = None
        self._holding = False
        self.connected.clear()
        # Everything unacked is sent again, in order, on the next connection.
        self._unacked.clear()

    def _contact(self) -> None:
        if self._cloud_monitor is not None and self._cloud_monitor.on_message(time.monotonic()) == "revert":
            self._spawn(self._revert_takeover())

    async def _replay_backlog(self) -> None:
        """Send every frame still owed, oldest first, before anything new."""
        self._replaying = True
        try:
            sent = 0
            for _, frame_id, text in self.outbox.backlog():
                if self.ws is None:
                    return
                await self.ws.send(text)
                self.cloud_bytes[1] += len(text)
                self._unacked[frame_id] = (time.monotonic() + 5.0, 1)
                sent += 1
            if sent:
                self.say(f"re-sent {sent} frame(s) kept while disconnected")
        finally:
            self._replaying = False

    async def _resend_loop(self) -> None:
        """Resend frames the cloud has not acked, with backoff, while connected."""
        while True:
            await asyncio.sleep(0.5)
            if self.ws is None or self._replaying:
                continue
            now = time.monotonic()
            due = [frame_id for frame_id, (at, _) in self._unacked.items() if at <= now]
            for frame_id in due:
                text = self.outbox.frame(frame_id)
                _, attempts = self._unacked.pop(frame_id)
                if text is None:
                    continue
                with contextlib.suppress(websockets.ConnectionClosed):
                    await self.ws.send(text)
                self._unacked[frame_id] = (now + min(30.0, 5.0 * 2**attempts), attempts + 1)

    async def emit(self, event: Event, data: Mapping[str, Any], *, reply_to: str | None = None) -> Envelope:
        """Send a frame to the cloud; one that changes state is kept on disk until acked."""
        envelope = protocol.make(event, dict(data), reply_to=reply_to, now=time.time())
        if event == Event.METRICS:
            self.metric_points_sent += len(data["metrics"])
        if event in protocol.REQUIRES_ACK:
            text = self.outbox.put(envelope)
            if self.ws is not None and not self._replaying and not self._holding:
                self._unacked[envelope.id] = (time.monotonic() + 5.0, 1)
                await self._send_text(text)
        else:
            await self._send_direct(envelope)
        return envelope

    async def _send_direct(self, envelope: Envelope) -> None:
        await self._send_text(protocol.encode(envelope))

    async def _send_text(self, text: str) -> None:
        ws = self.ws
        if ws is None:
            return
        try:
            await ws.send(text)
            self.cloud_bytes[1] += len(text)
        except websockets.ConnectionClosed:
            pass

    # ------------------------------------------------------------------ frames from the cloud

    def _receive(self, envelope: Envelope) -> None:
        event = envelope.event
        if event == Event.ACK:
            if envelope.reply_to:
                self.outbox.ack(envelope.reply_to)
                self._unacked.pop(envelope.reply_to, None)
            return
        if event == Event.ERROR_MESSAGE and envelope.reply_to:
            self._on_refused(envelope)
            return
        if event in protocol.REQUIRES_ACK and self._dedup.seen(envelope.id):
            if envelope.id in self._handling:
                return  # still being handled (a migration takes seconds): its answer comes when done
            # A retransmission of something already handled: answer it the same way again.
            answer = self._answers.get(envelope.id) or protocol.ack_text(envelope.id, now=time.time())
            self._spawn(self._send_text(answer))
            return
        self._spawn(self._handle(envelope))

    def _on_refused(self, envelope: Envelope) -> None:
        payload = protocol.parse_payload(envelope)
        frame_id = envelope.reply_to or ""
        if payload.code in RETRY_CODES:
            return  # kept: the resend loop tries again later
        text = self.outbox.frame(frame_id)
        self.outbox.ack(frame_id)
        self._unacked.pop(frame_id, None)
        self.say(f"the cloud refused a frame: {payload.message}")
        if text is None:
            return
        refused = protocol.decode(text)
        if refused.event == Event.COMPONENT_START:
            data = refused.data
            record = self.skills.get(data["skill"])
            if record is not None and record.locations.get(data["component"]) == "cloud":
                record.locations[data["component"]] = None
                self._spawn(self._set_status(record, data["component"], CS.FAILED, None, payload.message))

    async def _handle(self, envelope: Envelope) -> None:
        self._handling.add(envelope.id)
        try:
            await self._handle_once(envelope)
        finally:
            self._handling.discard(envelope.id)

    async def _handle_once(self, envelope: Envelope) -> None:
        handler = HANDLERS.get(envelope.event)
        try:
            if handler is None:
                raise ProtocolError(f"a robot does not handle {envelope.event}", code="unsupported")
            payload = protocol.parse_payload(envelope)
            if getattr(payload, "robot", None) not in (None, self.settings.robot):
                raise ProtocolError("addressed to another robot", field="data.robot", code="forbidden")
            reply = await handler(self, envelope, payload)
        except ProtocolError as exc:
            await self._answer(envelope, protocol.encode(protocol.error_frame(exc, envelope.id, now=time.time())))
            return
        except Exception as exc:
            logger.exception("handling %s failed", envelope.event)
            error = ProtocolError(str(exc) or type(exc).__name__, code="internal_error")
            await self._answer(envelope, protocol.encode(protocol.error_frame(error, envelope.id, now=time.time())))
            return
        if reply is not None:
            event, data = reply
            await self._answer(
                envelope, protocol.encode(protocol.make(event, data, reply_to=envelope.id, now=time.time()))
            )
        elif envelope.event in protocol.REQUIRES_ACK:
            await self._answer(envelope, protocol.ack_text(envelope.id, now=time.time()))

    async def _answer(self, envelope: Envelope, text: str) -> None:
        if envelope.event in protocol.REQUIRES_ACK:
            self._answers[envelope.id] = text
            if len(self._answers) > 2000:
                self._answers.pop(next(iter(self._answers)))
        await self._send_text(text)

    def _spawn(self, coroutine: Any) -> None:
        task = asyncio.get_running_loop().create_task(coroutine)
        self._handlers.add(task)
        task.add_done_callback(self._handlers.discard)

    # ------------------------------------------------------------------ config

    def apply_config(self, config: RobotConfig, *, source: str) -> None:
        """Make a validated robot config the one in force and keep it on disk."""
        first = not self.config_from_cloud.is_set()
        self.config = config
        if self._cloud_monitor is not None:
            self._cloud_monitor.disconnection_delay = config.connection_lost_after
        for name in ("cpu", "gpu", "ram", "bandwidth", "io"):
            setattr(self.monitor.robot, name, getattr(config.resources, name))
        if source == "cloud":
            self.config_from_cloud.set()
        self.network.apply_config(config)
        if config.subnets is not None and hasattr(self.runtime, "use_subnet"):
            self.runtime.use_subnet(config.subnets.local)
        self._save_soon()
        if first and source == "cloud":
            self.say(f"robot config received (heuristic {config.heuristic}, offloading {config.offloading})")

    def allocation_settings(self) -> AllocationSettings:
        """Return Algorithm 1's settings from the robot config."""
        config = self.config or RobotConfig()
        weights = Weights(**config.weights.model_dump())
        return AllocationSettings(
            heuristic=config.heuristic, threshold=config.threshold, weights=weights, per_gb=config.costs.per_gb
        )

    # ------------------------------------------------------------------ startup skills

    async def _startup(self) -> None:
        """Once the cloud sent a config, relaunch the Skills that ran before, in parallel."""
        await self.config_from_cloud.wait()
        wanted = [skill for skill, record in self.skills.items() if record.status in (SS.RUNNING, SS.STARTING)]
        if not wanted:
            self._startup_done = True
            return
        self.say(f"restarting {len(wanted)} skill(s) with their latest config from the cloud")
        limit = asyncio.Semaphore(self.settings.startup_parallelism)

        async def one(skill_id: str) -> None:
            async with limit:
                reply = await self.request(Event.SKILL_CONFIG_GET, {"skill": skill_id})
                if reply is None or reply.event != Event.SKILL_CONFIG:
                    self.say(f"skill {skill_id}: the cloud has no config for it any more; not restarted")
                    record = self.skills.pop(skill_id)
                    await self._stop_components(record, record.config.components)
                    return
                await self.start_skill(parse_skill_config(dict(reply.data["config"])))

        await asyncio.gather(*(one(skill_id) for skill_id in wanted), return_exceptions=True)
        self._startup_done = True

    async def request(self, event: Event, data: Mapping[str, Any], timeout: float = 10.0) -> Envelope | None:
        """Ask the cloud something and wait for the answer (None if it does not come)."""
        await self.connected.wait()
        future: asyncio.Future[Envelope] = asyncio.get_running_loop().create_future()
        envelope = protocol.make(event, dict(data), now=time.time())
        self._waiters[envelope.id] = future
        try:
            await self._send_direct(envelope)
            return await asyncio.wait_for(future, timeout)
        except TimeoutError:
            return None
        finally:
            self._waiters.pop(envelope.id, None)

    # ------------------------------------------------------------------ skills and components

    async def start_skill(self, config: SkillConfig, *, starting: Iterable[str] | None = None) -> SkillRecord:
        """Launch a Skill: place each component (Algorithm 1) and start it where it goes."""
        record = self.skills.get(config.skill_id)
        if record is None:
            record = self.skills[config.skill_id] = SkillRecord(config=config)
        else:
            record.config = config
        for component in config.components:
            record.locations.setdefault(component, None)
        await self._set_skill_status(record, SS.STARTING)
        if record.supervisor is None:
            record.supervisor = SkillSupervisor(
                config.skill_id, on_failure=functools.partial(self._plugin_failed, record)
            )
            record.supervisor.context["controller"] = self
            for name, plugin in self.plugins.items():
                record.supervisor.start(name, plugin)
            # The manager's Components API must listen before components get its URL.
            late = await record.supervisor.wait_ready(timeout=10.0)
            if late:
                self.say(f"skill {config.skill_id}: {', '.join(late)} not ready after 10 s; starting anyway")
        names = list(starting if starting is not None else config.components)
        results = await asyncio.gather(*(self.place_component(record, name) for name in names), return_exceptions=True)
        failures = [
            f"{name}: {result}" for name, result in zip(names, results, strict=True) if isinstance(result, Exception)
        ]
        if failures and len(failures) == len(names):
            await self._set_skill_status(record, SS.FAILED, "; ".join(failures)[:1900])
        else:
            await self._set_skill_status(record, SS.RUNNING, "; ".join(failures)[:1900] or None)
        return record

    async def stop_skill(self, skill_id: str) -> None:
        """Stop a Skill's components on the robot and in the cloud."""
        record = self._skill(skill_id)
        await self._set_skill_status(record, SS.STOPPING)
        await self._stop_components(record, record.config.components)
        if record.supervisor is not None:
            await record.supervisor.close()
            record.supervisor = None
        await self._set_skill_status(record, SS.STOPPED)

    async def _stop_components(self, record: SkillRecord, names: Iterable[str]) -> None:
        await asyncio.gather(*(self.stop_component(record, name) for name in names), return_exceptions=True)

    async def place_component(self, record: SkillRecord, name: str, *, location: str | None = None) -> str:
        """Start a component where it should run; return that location."""
        component = record.config.components[name]
        target = location or self._preferred_location(component.location, record.config.skill_id, name)
        if target == "cloud":
            if component.location == "robot":
                raise ProtocolError(f"component {name!r} may only run on the robot", field="data.location")
            await self._start_in_cloud(record, name)
            return "cloud"
        if component.location == "cloud":
            raise ProtocolError(f"component {name!r} may only run in the cloud", field="data.location")
        async with self._lock:
            decision = self.allocate(record.config.skill_id, name)
            if isinstance(decision, Replace):
                replaced = self.skills[decision.skill_id]
                self.say(
                    f"{record.config.skill_id}/{name}: moving {decision.skill_id}/{decision.component_id} "
                    f"to the cloud first ({decision.reason})"
                )
                for moved in (decision.component_id, *decision.links):
                    # A migration: the robot copy serves until its cloud copy runs and the router
                    # switches; if the cloud cannot run it, it stays and this placement fails saying why.
                    await self.migrate_component(replaced, moved, "cloud")
            elif isinstance(decision, Cloud):
                if location == "robot":
                    raise ProtocolError(f"no room on the robot for {name!r}: {decision.reason}", code="no_resources")
                await self._start_in_cloud(record, name)
                return "cloud"
            elif isinstance(decision, Refuse):
                await self._set_status(record, name, CS.FAILED, None, decision.reason)
                raise ProtocolError(f"no room on the robot for {name!r}: {decision.reason}", code="no_resources")
            await self._start_on_robot(record, name)
        return "robot"

    def _preferred_location(self, required: str, skill_id: str, name: str) -> str:
        if required in ("robot", "cloud"):
            return required
        mode = self.config.offloading if self.config else "auto"
        if mode == "auto":
            # Previous launches are the backbone of the first placement (thesis §3.4.1):
            # start where the manager last settled the component.
            return previous_placement(self.data_dir, skill_id).get(name, "robot")
        return "cloud" if mode == "cloud" else "robot"

    def allocate(self, skill_id: str, component_id: str) -> Decision:
        """Run Algorithm 1 for one component against the robot's state now."""
        total = (self.config or RobotConfig()).resources
        used = self._reserved()
        free = self.monitor.free(used)
        active = {
            (skill, name): where
            for skill, record in self.skills.items()
            for name, where in record.locations.items()
            if where is not None
        }
        measurements = {
            key: Measurement(usage=Resources(cpu=usage.cpu, ram=usage.ram)) for key, usage in self._usage.items()
        }
        configs = [record.config for record in self.skills.values()]
        state = allocation_state(total, Resources(**free), configs, active, measurements)
        return allocate(state, skill_id, component_id, self.allocation_settings())

    def _reserved(self) -> dict[str, float]:
        """Sum the declared needs of every component running on the robot."""
        used = dict.fromkeys(("cpu", "gpu", "ram", "bandwidth", "io"), 0.0)
        for record in self.skills.values():
            for name, where in record.locations.items():
                if where == "robot":
                    needs = record.config.components[name].resources
                    for key in used:
                        used[key] += getattr(needs, key)
        return used

    def component_spec(self, record: SkillRecord, name: str) -> ComponentSpec:
        """Build the launch spec of a robot-side component with the env contract."""
        component = record.config.components[name]
        launch = component.robot
        if launch is None:
            raise ProtocolError(f"component {name!r} has no robot launch spec", field=f"components.{name}.robot")
        env = {
            "BRIDGEOS_ROBOT": self.settings.robot,
            "BRIDGEOS_SKILL": record.config.skill_id,
            "BRIDGEOS_COMPONENT": name,
            "BRIDGEOS_LOCATION": "robot",
        }
        if self.ros_master:
            env["ROS_MASTER_URI"] = self.ros_master
        if component.ros:
            # The Skill Router relays between this namespace and the names peers use.
            env["ROS_NAMESPACE"] = instance_namespace(record.config.skill_id, name, "robot")
        if record.supervisor is not None:
            env.update({k: str(v) for k, v in record.supervisor.context.get("env", {}).items()})
        return ComponentSpec(
            robot=self.settings.robot,
            skill=record.config.skill_id,
            component=name,
            location="robot",
            launch=launch,
            resources=component.resources,
            env=env,
            volumes=tuple(record.config.volumes),
            ros=component.ros,
        )

    async def _start_on_robot(self, record: SkillRecord, name: str) -> None:
        spec = self.component_spec(record, name)
        await self._set_status(record, name, CS.STARTING, "robot")
        try:
            state = await self.runtime.start(spec)
        except RuntimeFailure as exc:
            await self._set_status(record, name, CS.FAILED, "robot", str(exc))
            raise ProtocolError(str(exc), code="launch_failed") from None
        record.locations[name] = "robot"
        self._route_first(record, name, "robot")
        await self._set_status(record, name, CS.RUNNING, "robot")
        await self.emit(
            Event.COMPONENT_LOCATION, {"skill": record.config.skill_id, "component": name, "location": "robot"}
        )
        container = {"runtime": self.runtime.name}
        ident = state.pid_or_container_id
        if isinstance(ident, int):
            container["pid"] = ident
        elif ident:
            container["id"] = str(ident)[:64]
        await self.emit(
            Event.COMPONENT_INFORMATION,
            {"skill": record.config.skill_id, "component": name, "location": "robot", "container": container},
        )
        self._save_soon()

    async def _start_in_cloud(self, record: SkillRecord, name: str, *, wait: float | None = None) -> None:
        """Forward a cloud-side launch to the cloud; with ``wait``, return once it runs there, raise if not."""
        data = {"skill": record.config.skill_id, "component": name, "location": "cloud"}
        if wait is None:
            record.locations[name] = "cloud"
            self._route_first(record, name, "cloud")
            await self._set_status(record, name, CS.STARTING, "cloud")
            await self.emit(Event.COMPONENT_START, data)
            self._save_soon()
            return
        key = (record.config.skill_id, name)
        reported = self._cloud_waiters[key] = asyncio.get_running_loop().create_future()
        try:
            await self.emit(Event.COMPONENT_START, data)
            status, message = await asyncio.wait_for(asyncio.shield(reported), wait)
        except TimeoutError:
            await self.emit(Event.COMPONENT_STOP, data)  # a copy that comes up later must not linger
            raise ProtocolError(f"the cloud did not run {name!r} within {wait:g} s", code="cloud_timeout") from None
        finally:
            if self._cloud_waiters.get(key) is reported:
                del self._cloud_waiters[key]
        if status != CS.RUNNING:
            raise ProtocolError(f"the cloud could not run {name!r}: {message or status}", code="launch_failed")
        record.locations[name] = "cloud"
        self._route_first(record, name, "cloud")
        self._save_soon()

    def on_cloud_report(self, skill_id: str, name: str, status: str, message: str | None) -> None:
        """Take in what the cloud says of a component's cloud copy (running, restarting, failed)."""
        waiter = self._cloud_waiters.get((skill_id, name))
        if waiter is not None:
            if not waiter.done() and status in (CS.RUNNING, CS.FAILED):
                waiter.set_result((status, message))
            return
        record = self.skills.get(skill_id)
        if record is None or record.locations.get(name) != "cloud":
            return  # a copy being retired, or a move still deciding: nothing changes here
        record.statuses[name] = CS(status)
        if status == CS.FAILED:
            record.locations[name] = None
            self.say(f"{skill_id}/{name}: its cloud copy failed: {message or 'no reason given'}")
            self._save_soon()

    async def stop_component(self, record: SkillRecord, name: str, *, only: str | None = None) -> None:
        """Stop a component where it runs (or only at ``only``)."""
        where = record.locations.get(name)
        skill_id = record.config.skill_id
        if where == "robot" and only in (None, "robot"):
            await self._set_status(record, name, CS.STOPPING, "robot")
            await self.runtime.stop(skill_id, name)
        elif where == "cloud" and only in (None, "cloud"):
            await self.emit(Event.COMPONENT_STOP, {"skill": skill_id, "component": name, "location": "cloud"})
        if only is None or only == where:
            record.locations[name] = None
            self._route(record, name, None)
            await self._set_status(record, name, CS.STOPPED, None)
        self._reporter.forget(skill_id, name)
        self._usage.pop((skill_id, name), None)
        self._save_soon()

    async def migrate_component(self, record: SkillRecord, name: str, target: str | None) -> str:
        """Move a running component to the other side: start there first, then stop here."""
        component = record.config.components[name]
        current = record.locations.get(name)
        if component.location != "either":
            raise ProtocolError(f"component {name!r} may only run on the {component.location}", field="data.component")
        target = target or ("robot" if current == "cloud" else "cloud")
        if target == current:
            return target
        await self._set_status(record, name, CS.MIGRATING, current)
        # The old copy keeps serving until the new one runs and the router switches (no downtime window).
        try:
            if target == "robot":
                await self.place_component(record, name, location="robot")
            else:
                # Nothing switches before the cloud reports its copy running.
                await self._start_in_cloud(record, name, wait=self.settings.cloud_start_timeout)
        except Exception as exc:
            # Rolled back: the component keeps running where it was, and the cloud hears why.
            self.metrics.migrated(record.config.skill_id, "failed")
            record.locations[name] = current
            await self._set_status(record, name, CS.RUNNING if current else CS.STOPPED, current, f"not moved: {exc}")
            raise
        router = self._router(record)
        if router is not None and current is not None:
            if not await router.wait_ready(name, target, router.settings.ready_timeout):
                self.metrics.migrated(record.config.skill_id, "abandoned")
                await self._abandon_migration(record, name, target, current)
                raise ProtocolError(
                    f"component {name!r} was not ready on the {target} within {router.settings.ready_timeout:g} s; "
                    f"it keeps running on the {current}",
                    field="data.component",
                    code="migration_failed",
                )
            await router.switch(name, target)
        elif router is not None:
            router.set_active(name, target)
        if current == "cloud":
            await self.emit(
                Event.COMPONENT_STOP, {"skill": record.config.skill_id, "component": name, "location": "cloud"}
            )
        elif current == "robot":
            await self.runtime.stop(record.config.skill_id, name)
            self._usage.pop((record.config.skill_id, name), None)
        await self.emit(
            Event.COMPONENT_LOCATION, {"skill": record.config.skill_id, "component": name, "location": target}
        )
        if target == "cloud":
            await self._set_status(record, name, CS.RUNNING, "cloud")
        self.metrics.migrated(record.config.skill_id, "done")
        return target

    async def _abandon_migration(self, record: SkillRecord, name: str, target: str, current: str) -> None:
        """Stop the copy that did not get ready and keep the old one in charge."""
        skill_id = record.config.skill_id
        if target == "robot":
            await self.runtime.stop(skill_id, name)
        else:
            await self.emit(Event.COMPONENT_STOP, {"skill": skill_id, "component": name, "location": "cloud"})
        record.locations[name] = current
        await self._set_status(record, name, CS.RUNNING, current, f"migration to the {target} abandoned: not ready")
        await self.emit(Event.COMPONENT_LOCATION, {"skill": skill_id, "component": name, "location": current})
        self._save_soon()

    def _router(self, record: SkillRecord) -> Any:
        """Return the Skill's router, if it runs one."""
        return record.supervisor.context.get("router") if record.supervisor is not None else None

    def _route(self, record: SkillRecord, name: str, location: str | None) -> None:
        """Point the Skill's router at one instance of a component (or at none)."""
        router = self._router(record)
        if router is not None:
            with contextlib.suppress(ValueError):
                router.set_active(name, location)

    def _route_first(self, record: SkillRecord, name: str, location: str) -> None:
        """Let the router follow a component's first start (a migration switches it instead)."""
        router = self._router(record)
        if router is not None and router.active(name) is None:
            self._route(record, name, location)

    async def _set_status(
        self, record: SkillRecord, name: str, status: CS, location: str | None, message: str | None = None
    ) -> None:
        record.statuses[name] = status
        data: dict[str, Any] = {"skill": record.config.skill_id, "component": name, "status": str(status)}
        if location:
            data["location"] = location
        if message:
            data["message"] = message[:1900]
        await self.emit(Event.COMPONENT_STATUS, data)

    async def _set_skill_status(self, record: SkillRecord, status: SS, message: str | None = None) -> None:
        record.status = status
        data: dict[str, Any] = {"skill": record.config.skill_id, "status": str(status)}
        if message:
            data["message"] = message
        await self.emit(Event.SKILL_STATUS, data)
        self._save_soon()

    def _plugin_failed(self, record: SkillRecord, name: str, message: str) -> None:
        self._spawn(self._set_skill_status(record, SS.FAILED, message))

    def _on_runtime_status(self, state: ComponentState) -> None:
        """Report a component's crash, restart or give-up that the runtime saw."""
        record = self.skills.get(state.skill)
        if record is None or state.component not in record.config.components:
            return
        if state.status == Status.RESTARTING:
            self.metrics.component_restarted(state.skill, state.component)
        mapped = {
            Status.RUNNING: CS.RUNNING,
            Status.STARTING: CS.STARTING,
            Status.RESTARTING: CS.STARTING,
            Status.FAILED: CS.FAILED,
            Status.EXITED: CS.STOPPED,
        }.get(state.status)
        if mapped is None or record.locations.get(state.component) != "robot":
            return
        if record.statuses.get(state.component) == mapped:
            return
        message = None
        if state.status == Status.RESTARTING:
            message = f"crashed (exit code {state.exit_code}); restart {state.restarts}"
        elif state.status == Status.FAILED:
            message = f"crashed too often (exit code {state.exit_code}); gave up"
        self._spawn(self._set_status(record, state.component, mapped, "robot", message))

    def _skill(self, skill_id: str) -> SkillRecord:
        record = self.skills.get(skill_id)
        if record is None:
            raise ProtocolError(f"no skill {skill_id!r} on this robot", field="data.skill", code="not_found")
        return record

    def _component(self, skill_id: str, name: str) -> SkillRecord:
        record = self._skill(skill_id)
        if name not in record.config.components:
            raise ProtocolError(
                f"skill {skill_id!r} has no component {name!r}", field="data.component", code="not_found"
            )
        return record

    # ------------------------------------------------------------------ monitoring

    async def _monitor_loop(self) -> None:
        """Sample the robot and its components; send what changed enough, or is due."""
        interval = self.settings.sample_interval
        stats_every = max(1, round(5.0 / interval)) if self.runtime.name == "docker" else 1
        tick = 0
        last_cloud = (0, 0, time.monotonic())
        while True:
            await asyncio.sleep(interval)
            tick += 1
            if tick % stats_every == 0:
                with contextlib.suppress(Exception):
                    self._usage = await self.runtime.stats()
            now = time.monotonic()
            span = max(1e-3, now - last_cloud[2])
            cloud_rates = ((self.cloud_bytes[0] - last_cloud[0]) / span, (self.cloud_bytes[1] - last_cloud[1]) / span)
            last_cloud = (self.cloud_bytes[0], self.cloud_bytes[1], now)
            sample = self.monitor.sample(self._reserved(), cloud_rates)
            readings: list[tuple[str, float, str | None, str | None]] = [
                (name, float(value), None, None) for name, value in sample.values.items()
            ]
            for (skill, component), usage in self._usage.items():
                readings.append(("cpu", round(100 * usage.cpu, 2), skill, component))
                readings.append(("ram", round(usage.ram, 1), skill, component))
            points = self._reporter.select(time.time(), readings)
            if points:
                await self.emit(Event.METRICS, {"metrics": points})

    # ------------------------------------------------------------------ cloud role takeover (Algorithm 7)

    async def _takeover_loop(self) -> None:
        while True:
            await asyncio.sleep(0.25)
            if self.ws is not None:
                self._contact()  # the socket's keepalive closes it when pongs stop
                continue
            if self._cloud_monitor is not None and self._cloud_monitor.tick(time.monotonic()) == "takeover":
                await self._take_over()

    async def _take_over(self) -> None:
        """Run locally the cloud part of every Skill that can run whole on the robot."""
        self.say("cloud lost: taking over its role")
        for record in self.skills.values():
            if record.supervisor is not None:
                record.supervisor.context["cloud"] = "lost"
                record.supervisor.notify("connection_lost")
        active = {
            (skill, name): where
            for skill, record in self.skills.items()
            if record.status in (SS.RUNNING, SS.STARTING)
            for name, where in record.locations.items()
            if where is not None
        }
        running = [r.config for r in self.skills.values() if r.status in (SS.RUNNING, SS.STARTING)]
        free = Resources(**self.monitor.free(self._reserved()))
        state = allocation_state((self.config or RobotConfig()).resources, free, running, active)
        plan = plan_takeover(state.skills, free)
        for skill_id, names in plan.items():
            record = self.skills[skill_id]
            started = []
            for name in names:
                try:
                    await self.runtime.start(self.component_spec(record, name))
                except (RuntimeFailure, ProtocolError) as exc:
                    self.say(f"takeover: {skill_id}/{name} could not start on the robot: {exc}")
                    continue
                started.append(name)
                record.statuses[name] = CS.RUNNING
                self._route(record, name, "robot")
            if started:
                self._takeover[skill_id] = started
        count = sum(len(names) for names in self._takeover.values())
        self.say(f"takeover: {count} cloud component(s) now run on the robot")

    async def _revert_takeover(self) -> None:
        """The cloud is back: hand its components back and stop the local duplicates."""
        migrations, self._takeover = self._takeover, {}
        for record in self.skills.values():
            if record.supervisor is not None:
                record.supervisor.context["cloud"] = "connected"
                record.supervisor.notify("connection_established")
        stopped = 0
        for skill_id, names in migrations.items():
            record = self.skills.get(skill_id)
            for name in names:
                if record is not None and record.locations.get(name) == "cloud":
                    self._route(record, name, "cloud")
                await self.runtime.stop(skill_id, name)
                stopped += 1
                if record is not None and record.locations.get(name) == "cloud":
                    await self._set_status(record, name, CS.RUNNING, "cloud")
        self.say(f"cloud back: {stopped} local duplicate(s) stopped")

    def takeover_components(self) -> dict[str, list[str]]:
        """Return the cloud components running on the robot because the cloud is lost."""
        return {skill: list(names) for skill, names in self._takeover.items()}


# ---------------------------------------------------------------------- command handlers

Handler = Callable[[RobotController, Envelope, Any], Any]
HANDLERS: dict[str, Handler] = {}


def handles(*events: Event) -> Callable[[Handler], Handler]:
    """Register a handler of cloud frames; it returns (event, data) to reply, or None to ack."""

    def register(function: Handler) -> Handler:
        for event in events:
            HANDLERS[event] = function
        return function

    return register


def _not_before_config(controller: RobotController) -> None:
    if not controller.config_from_cloud.is_set():
        raise ProtocolError("no robot config from the cloud yet; skills wait for one", code="invalid_state")


@handles(Event.ROBOT_CONFIG)
async def on_robot_config(controller: RobotController, envelope: Envelope, p: Any) -> None:
    try:
        config = parse_robot_config(dict(p.config))
    except ValueError as exc:
        raise ProtocolError(_first_error(exc), field="data.config", code="invalid_config") from None
    controller.apply_config(config, source="cloud")
    if envelope.reply_to is not None and envelope.reply_to in controller._waiters:
        controller._waiters[envelope.reply_to].set_result(envelope)


@handles(Event.ROBOT_CONFIG_UPDATE)
async def on_robot_config_update(controller: RobotController, envelope: Envelope, p: Any) -> None:
    base = (controller.config or RobotConfig()).model_dump(mode="json")
    try:
        config = parse_robot_config(merge_config_changes(base, p.changes))
    except ValueError as exc:
        raise ProtocolError(_first_error(exc), field="data.changes", code="invalid_config") from None
    controller.apply_config(config, source="cloud")


@handles(Event.OFFLOADING)
async def on_offloading(controller: RobotController, envelope: Envelope, p: Any) -> None:
    base = (controller.config or RobotConfig()).model_dump(mode="json")
    controller.apply_config(parse_robot_config({**base, "offloading": str(p.mode)}), source="cloud")


@handles(Event.OFFLOADING_GET)
async def on_offloading_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    return Event.OFFLOADING, {"mode": (controller.config or RobotConfig()).offloading}


@handles(Event.SKILL_START)
async def on_skill_start(controller: RobotController, envelope: Envelope, p: Any) -> None:
    _not_before_config(controller)
    if p.config is None:
        record = controller._skill(p.skill)
        config = record.config
    else:
        try:
            config = parse_skill_config(dict(p.config))
        except ValueError as exc:
            raise ProtocolError(_first_error(exc), field="data.config", code="invalid_config") from None
        if config.skill_id != p.skill:
            raise ProtocolError(
                f"config is for skill {config.skill_id!r}, not {p.skill!r}", field="data.config.skill_id"
            )
    # Accepted: ack now, launch in the background and report progress as statuses.
    controller._spawn(controller.start_skill(config))


@handles(Event.SKILL_STOP)
async def on_skill_stop(controller: RobotController, envelope: Envelope, p: Any) -> None:
    controller._skill(p.skill)
    controller._spawn(controller.stop_skill(p.skill))


@handles(Event.SKILL_STATUS_GET)
async def on_skill_status_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    return Event.SKILL_STATUS, {"skill": p.skill, "status": str(controller._skill(p.skill).status)}


@handles(Event.SKILL_CONFIG)
async def on_skill_config(controller: RobotController, envelope: Envelope, p: Any) -> None:
    waiter = controller._waiters.get(envelope.reply_to or "")
    if waiter is not None and not waiter.done():
        waiter.set_result(envelope)
        return
    record = controller.skills.get(p.skill)
    if record is not None:
        try:
            record.config = parse_skill_config(dict(p.config))
        except ValueError as exc:
            raise ProtocolError(_first_error(exc), field="data.config", code="invalid_config") from None


@handles(Event.COMPONENT_START)
async def on_component_start(controller: RobotController, envelope: Envelope, p: Any) -> None:
    _not_before_config(controller)
    record = controller._component(p.skill, p.component)
    await controller.place_component(record, p.component, location=str(p.location))


@handles(Event.COMPONENT_STOP)
async def on_component_stop(controller: RobotController, envelope: Envelope, p: Any) -> None:
    record = controller._component(p.skill, p.component)
    await controller.stop_component(record, p.component, only=str(p.location) if p.location else None)


@handles(Event.COMPONENT_MIGRATE)
async def on_component_migrate(controller: RobotController, envelope: Envelope, p: Any) -> None:
    _not_before_config(controller)
    record = controller._component(p.skill, p.component)
    await controller.migrate_component(record, p.component, str(p.location) if p.location else None)


@handles(Event.COMPONENT_STATUS)
async def on_component_status(controller: RobotController, envelope: Envelope, p: Any) -> None:
    # The cloud reports its copy of a component (started, restarting after a crash, failed).
    if p.location == "cloud" and p.skill in controller.skills:
        controller.on_cloud_report(p.skill, p.component, str(p.status), p.message)


@handles(Event.COMPONENT_INFORMATION)
async def on_component_information(controller: RobotController, envelope: Envelope, p: Any) -> None:
    # Where an instance is reached (the cloud sends its copies' address and published ports): kept for
    # the Skill Router's HTTP routes. A Skill or component this robot no longer has is ignored.
    record = controller.skills.get(p.skill)
    if record is None or p.component not in record.config.components:
        return
    container = p.container.model_dump(mode="json", exclude_none=True)
    if p.location == "cloud":
        record.cloud_containers[p.component] = container
    router = controller._router(record)
    if router is not None:
        router.set_container(p.component, str(p.location), container)


@handles(Event.METRICS)
async def on_cloud_metrics(controller: RobotController, envelope: Envelope, p: Any) -> None:
    # The cloud's measurements of this robot's cloud copies, for each Skill's manager.
    by_skill: dict[str, list[dict[str, Any]]] = {}
    for point in p.metrics:
        if point.skill and point.component:
            by_skill.setdefault(point.skill, []).append(point.model_dump(mode="json", exclude_none=True))
    for skill_id, points in by_skill.items():
        record = controller.skills.get(skill_id)
        manager = record.supervisor.context.get("manager") if record and record.supervisor else None
        store = getattr(manager, "store", None)
        if store is not None:
            store.publish(points)


@handles(Event.VOLUME_CHANGES)
async def on_volume_changes(controller: RobotController, envelope: Envelope, p: Any) -> None:
    await controller.volumes.receive(p)


@handles(Event.VOLUME_CHUNKS_GET)
async def on_volume_chunks_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    return Event.VOLUME_CHUNKS, await controller.volumes.chunks(p)


@handles(Event.VOLUME_CHUNKS)
async def on_volume_chunks(controller: RobotController, envelope: Envelope, p: Any) -> None:
    waiter = controller._waiters.get(envelope.reply_to or "")
    if waiter is not None and not waiter.done():
        waiter.set_result(envelope)


@handles(Event.COMPONENT_STATUS_GET)
async def on_component_status_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    record = controller._component(p.skill, p.component)
    data = {"skill": p.skill, "component": p.component, "status": str(record.statuses.get(p.component, CS.STOPPED))}
    if record.locations.get(p.component):
        data["location"] = record.locations[p.component]
    return Event.COMPONENT_STATUS, data


@handles(Event.ROBOT_STOP)
async def on_robot_stop(controller: RobotController, envelope: Envelope, p: Any) -> None:
    for skill_id, record in list(controller.skills.items()):
        if record.status in (SS.RUNNING, SS.STARTING):
            controller._spawn(controller.stop_skill(skill_id))


@handles(Event.ROBOT_START)
async def on_robot_start(controller: RobotController, envelope: Envelope, p: Any) -> None:
    _not_before_config(controller)
    for record in list(controller.skills.values()):
        if record.status in (SS.STOPPED, SS.FAILED):
            controller._spawn(controller.start_skill(record.config))


@handles(Event.SHUTDOWN)
async def on_shutdown(controller: RobotController, envelope: Envelope, p: Any) -> None:
    async def shut_down() -> None:
        for skill_id in list(controller.skills):
            with contextlib.suppress(Exception):
                await controller.stop_skill(skill_id)
        await controller.emit(Event.SHUTDOWN, {"reason": p.reason or "ordered by the cloud"})
        await asyncio.sleep(0.5)  # let the report and its ack cross
        controller.stop(0)

    controller._spawn(shut_down())


@handles(Event.CONNECTION_ESTABLISHED)
async def on_connection_established(controller: RobotController, envelope: Envelope, p: Any) -> None:
    return None


@handles(Event.METRICS_GET)
async def on_metrics_get(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    latest = controller.monitor.latest
    now = time.time()
    values = latest.values if latest else {}
    names = set(p.names) if p.names else None
    points = [
        {"name": name, "value": float(value), "ts": now}
        for name, value in values.items()
        if names is None or name in names
    ]
    return Event.METRICS, {"metrics": points[: p.limit or len(points)]}


@handles(Event.COMPONENTS_API)
async def on_components_api(controller: RobotController, envelope: Envelope, p: Any) -> tuple[Event, dict]:
    record = controller.skills.get(p.skill)
    env = record.supervisor.context.get("env", {}) if record is not None and record.supervisor is not None else {}
    url = env.get("BRIDGEOS_MANAGER_URL")
    if not url:
        raise ProtocolError(f"skill {p.skill!r} runs no manager on this robot", field="data.skill", code="not_found")
    status, body = await call_components_api(url, p.method, p.path, p.query, p.body)
    return Event.COMPONENTS_API_REPLY, {"skill": p.skill, "status": status, "body": body}


async def call_components_api(
    base: str, method: str, path: str, query: str, body: Mapping[str, Any] | None
) -> tuple[int, Any]:
    """Call a Skill's Components API on this robot; return its status and JSON answer."""
    import aiohttp

    url = base.rstrip("/") + path + (f"?{query}" if query else "")
    timeout = aiohttp.ClientTimeout(total=10)
    async with aiohttp.ClientSession(timeout=timeout) as session, session.request(method, url, json=body) as answer:
        try:
            return answer.status, await answer.json(content_type=None)
        except ValueError:
            return answer.status, {"error": (await answer.text())[:2000]}


def ws_scheme(ws: Any) -> str:
    """Name the scheme of a live connection (WSS or plain WS)."""
    return "WSS" if getattr(ws, "transport", None) and ws.transport.get_extra_info("sslcontext") else "WS"


def previous_placement(data_dir: Path, skill_id: str) -> dict[str, str]:
    """Return where each movable component of a Skill ran when its manager last stopped."""
    try:
        saved = json.loads((data_dir / "models" / skill_id / "placement.json").read_text())
    except (OSError, ValueError):
        return {}
    if not isinstance(saved, dict):
        return {}
    return {name: where for name, where in saved.items() if where in ("robot", "cloud")}


def _first_error(exc: ValueError) -> str:
    errors = field_errors(exc) if isinstance(exc, ValidationError) else None
    if errors:
        path, messages = next(iter(errors.items()))
        return f"{path}: {messages[0]}" if path else messages[0]
    return str(exc).splitlines()[0]
