"""Process glue of `bridgeos-agent run` and `bridgeos-agent doctor`: logging, signals, checks."""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import ipaddress
import logging
import os
import shutil
import signal
import socket
import ssl
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import psutil
import websockets

from bridgeos_agent import __version__, metrics, protocol, tls
from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.monitor import SimulatedRobot
from bridgeos_agent.protocol import Event
from bridgeos_agent.robotconfig import RobotConfig, parse_robot_config
from bridgeos_agent.rosmaster import find_ros_master
from bridgeos_agent.tls import is_loopback

__all__ = ["doctor", "run_agent", "settings_from_args"]


def settings_from_args(args: argparse.Namespace) -> AgentSettings:
    """Turn checked command-line options into the controller's settings."""
    data_dir = args.data_dir or Path.home() / ".local" / "share" / "bridgeos-agent" / args.robot
    simulated = None
    if args.simulate:
        low = args.sim_bandwidth_min if args.sim_bandwidth_min is not None else args.sim_bandwidth / 20
        simulated = SimulatedRobot(cpu=args.sim_cpu, ram=args.sim_ram, bandwidth=args.sim_bandwidth, bandwidth_min=low)
    return AgentSettings(
        master=args.master,
        robot=args.robot,
        token=args.token,
        token_file=args.token_file,
        data_dir=Path(data_dir),
        runtime=args.runtime,
        simulate=args.simulate,
        simulated=simulated,
        ros2=args.ros2,
        sample_interval=args.sample_interval,
        report_interval=args.report_interval,
        outbox_memory_bytes=int(args.outbox_memory * 1024 * 1024),
        stop_components_on_exit=args.stop_components_on_exit,
        ca_file=args.ca,
        allow_insecure=args.allow_insecure,
        vpn_device=args.vpn_device,
        firewall=args.firewall,
        labels=getattr(args, "labels", None) or {},
    )


class LevelTagged(logging.Formatter):
    """Format a record as its time and message, naming its level when it is a warning or worse."""

    def __init__(self) -> None:
        super().__init__("%(asctime)s %(message)s", datefmt="%H:%M:%S")

    def formatMessage(self, record: logging.LogRecord) -> str:
        line = super().formatMessage(record)
        if record.levelno < logging.WARNING:
            return line
        # An operator (or a log check) finds what went wrong by its level, as in every other log.
        stamp, _, message = line.partition(" ")
        return f"{stamp} {record.levelname} {message}"


def run_agent(args: argparse.Namespace) -> int:
    """Run the Robot Controller until SIGINT/SIGTERM, a shutdown order or a refused token."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(LevelTagged())
    logging.basicConfig(level=logging.WARNING if args.quiet else logging.INFO, handlers=[handler])
    settings = settings_from_args(args)
    logging.getLogger("bridgeos_agent").info(
        "bridgeos-agent %s: robot %s, runtime %s%s, data in %s",
        __version__,
        settings.robot,
        settings.runtime,
        ", simulated" if settings.simulate else "",
        settings.data_dir,
    )

    async def main() -> int:
        try:
            controller = RobotController(settings)
        except Exception as exc:  # e.g. Docker unreachable: say it and how to fix it
            logging.getLogger("bridgeos_agent").error("cannot start: %s", exc)
            return 1
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(signum, controller.stop)
        exporter = None
        if args.metrics:
            try:
                exporter = await metrics.serve(controller, args.metrics)
            except OSError as exc:
                logging.getLogger("bridgeos_agent").error("cannot serve metrics on %s: %s", args.metrics, exc)
                return 1
            logging.getLogger("bridgeos_agent").info("metrics on http://%s/metrics", args.metrics)
        doors: list[Any] = []
        # Before the controller runs: the robot's ROS 2 Context must be made before any cloud graph's.
        for option, address, ros in (
            ("rosbridge", args.rosbridge, args.rosbridge_ros),
            ("foxglove", args.foxglove, args.foxglove_ros),
        ):
            if not address:
                continue
            try:
                doors.append(await _serve_door(option, address, ros))
            except Exception as exc:  # no master, no rclpy, port taken: say which and stop
                logging.getLogger("bridgeos_agent").error("cannot serve %s on %s: %s", option, address, exc)
                for door in doors:
                    await door.close()
                if exporter is not None:
                    await exporter.cleanup()
                return 1
        try:
            return await controller.run()
        finally:
            for door in doors:
                await door.close()
            if exporter is not None:
                await exporter.cleanup()

    return asyncio.run(main())


async def _serve_door(kind: str, address: str, ros: str) -> Any:
    """Serve a robot-local door (rosbridge or foxglove) on the ROS 1 or 2 graph (auto: ROS 1 if a master answers)."""
    from bridgeos_agent.bridges.server import FoxgloveServer, RosbridgeServer, open_graph, parse_address

    host, port = parse_address(address)
    if ros == "auto":
        ros = "ros1" if find_ros_master() else "ros2"
    rosbridge = kind == "rosbridge"
    graph = await open_graph(ros) if rosbridge else await open_graph(ros, name="bridgeos_foxglove")
    server = RosbridgeServer(graph) if rosbridge else FoxgloveServer(graph)
    what = "rosbridge v2" if rosbridge else "Foxglove WebSocket"
    try:
        await server.start(host, port)
    except BaseException:
        await graph.close()
        raise
    logging.getLogger("bridgeos_agent").info(
        "%s for the robot's %s graph on ws://%s:%d (unauthenticated)", what, ros.upper(), host, server.port
    )
    return server


def doctor(args: argparse.Namespace) -> int:
    """Print one line per check with how to fix what fails; exit 0 when the agent can run."""
    results: list[tuple[bool, bool, str]] = []  # (ok, essential, line)

    def check(ok: bool, essential: bool, good: str, bad: str) -> None:
        results.append((ok, essential, good if ok else bad))
        print(f"{'ok  ' if ok else 'FAIL' if essential else 'warn'}  {good if ok else bad}")

    context = tls.client_context(ca_file=args.ca) if args.master.startswith("wss://") else None
    reachable, refused, config = asyncio.run(_probe_cloud(args.master, args.robot, args.token, context))
    check(
        reachable is True,
        True,
        f"cloud reachable at {args.master}",
        f"cannot reach the cloud at {args.master}: {reachable}. Check the URL and that the cloud runs.",
    )
    if context is not None:
        tls_ok = reachable is True or "CERTIFICATE" not in str(reachable).upper()
        check(
            tls_ok,
            True,
            f"TLS: the cloud's certificate verifies ({'--ca ' + str(args.ca) if args.ca else 'system CAs'})",
            f"TLS: the cloud's certificate does not verify ({reachable}); pass the CA that signs it with --ca",
        )
    else:
        check(
            is_loopback(urlsplit(args.master).hostname or ""),
            False,
            "plain ws:// on this machine (no TLS needed)",
            "plain ws:// to another machine: the token travels unencrypted; use wss://",
        )
    if reachable is True:
        check(
            refused is None,
            True,
            f"robot {args.robot} is accepted with this token",
            f"the cloud refused robot {args.robot}: {refused}. Ask the operator for the robot's token "
            "(python manage.py create_robot, or rotate it in the admin).",
        )
    if config is not None:
        _check_network(config, args, check)
    if args.runtime == "docker":
        docker_ok, docker_detail = _docker_status()
        check(docker_ok, True, f"Docker answers ({docker_detail})", f"Docker: {docker_detail}")
    else:
        docker_ok, docker_detail = _docker_status()
        check(
            docker_ok,
            False,
            f"Docker answers ({docker_detail})",
            f"Docker not usable ({docker_detail}); the process runtime works without it",
        )
    master = find_ros_master()
    check(
        master is not None,
        False,
        f"ROS master at {master}",
        "no ROS master (ROS_MASTER_URI or 127.0.0.1:11311); the agent will ask the cloud for one, "
        "or start one with `roscore`",
    )
    memory = psutil.virtual_memory()
    free_disk = shutil.disk_usage(Path.home()).free
    check(
        memory.available > 256 * 2**20,
        False,
        f"{memory.available / 2**20:.0f} MiB memory available, {psutil.cpu_count()} CPU(s)",
        f"only {memory.available / 2**20:.0f} MiB memory available; components may not fit",
    )
    check(
        free_disk > 512 * 2**20,
        False,
        f"{free_disk / 2**30:.1f} GiB free disk for the outbox and logs",
        f"only {free_disk / 2**20:.0f} MiB free disk; the outbox may fill",
    )
    failed = [line for ok, essential, line in results if essential and not ok]
    print(
        "ready: `bridgeos-agent run` will work" if not failed else f"not ready: {len(failed)} essential check(s) failed"
    )
    return 0 if not failed else 1


async def _probe_cloud(
    master: str, robot: str, token: str, context: ssl.SSLContext | None
) -> tuple[bool | str, str | None, RobotConfig | None]:
    """Connect and authenticate once; return (True or why unreachable, refusal reason or None, robot config)."""
    url = master.rstrip("/") + "/ws/robot/"
    options: dict[str, Any] = {"ssl": context} if context is not None else {}
    config = None
    try:
        async with websockets.connect(url, open_timeout=5, compression=None, proxy=None, **options) as ws:
            request = protocol.make(Event.AUTHENTICATION_ROBOT, {"robot": robot, "token": token}, now=time.time())
            await ws.send(protocol.encode(request))
            answer = protocol.decode(await asyncio.wait_for(ws.recv(), 5))
            if answer.event == Event.AUTHENTICATION_SUCCESS:
                with contextlib.suppress(TimeoutError, ValueError, websockets.WebSocketException):
                    async with asyncio.timeout(5):
                        while config is None:
                            frame = protocol.decode(await ws.recv())
                            if frame.event == Event.ROBOT_CONFIG:
                                config = parse_robot_config(dict(frame.data["config"]))
    except (OSError, TimeoutError, websockets.WebSocketException, protocol.ProtocolError) as exc:
        return (str(exc) or type(exc).__name__), None, None
    if answer.event == Event.AUTHENTICATION_SUCCESS:
        return True, None, config
    return True, getattr(protocol.parse_payload(answer), "reason", answer.event), None


def _check_network(config: RobotConfig, args: argparse.Namespace, check: Callable[..., None]) -> None:
    """Check the robot's subnets against this machine's networks, and what the tunnel needs."""
    if config.subnets is None:
        check(False, False, "", "no subnets in the robot config yet (the cloud allocates them)")
    else:
        own = {ipaddress.ip_network(config.subnets.local), ipaddress.ip_network(config.subnets.cloud)}
        clashes = []
        for name, addresses in psutil.net_if_addrs().items():
            if name == args.vpn_device:
                continue
            for address in addresses:
                if address.family != socket.AF_INET or not address.netmask:
                    continue
                interface = ipaddress.ip_interface(f"{address.address}/{address.netmask}")
                # The robot's own Docker bridge carries the local subnet: that is not a clash.
                if interface.network in own:
                    continue
                clashes += [
                    f"{name} {interface.network} overlaps {net}" for net in own if interface.network.overlaps(net)
                ]
        check(
            not clashes,
            True,
            f"subnets local {config.subnets.local} and cloud {config.subnets.cloud} are free on this machine",
            "subnets clash with this machine's networks: " + "; ".join(clashes) + ". Ask the operator for others.",
        )
    if not config.vpn.enabled:
        check(True, False, "VPN off in the robot config: the agent talks to the cloud over WSS", "")
        return
    openvpn = shutil.which("openvpn")
    check(openvpn is not None, True, f"OpenVPN at {openvpn}", "OpenVPN missing: sudo apt-get install openvpn")
    check(
        os.path.exists("/dev/net/tun"),
        True,
        "/dev/net/tun present",
        "/dev/net/tun missing: load the tun module (modprobe tun) or give the container the device",
    )
    up = [
        address.address
        for address in psutil.net_if_addrs().get(args.vpn_device, [])
        if address.family == socket.AF_INET
    ]
    check(
        bool(up),
        False,
        f"tunnel {args.vpn_device} up with address {', '.join(up)}",
        f"tunnel {args.vpn_device} not up now (bridgeos-agent run brings it up; without it the agent uses WSS)",
    )


def _docker_status() -> tuple[bool, str]:
    try:
        import docker.client
    except ImportError:
        return False, "the docker Python package is missing: pip install docker"
    try:
        client = docker.client.from_env(timeout=3)
        version = client.version().get("Version", "?")
        client.close()
    except Exception as exc:
        socket = os.environ.get("DOCKER_HOST", "/var/run/docker.sock")
        return False, f"no Docker engine at {socket} ({type(exc).__name__}); install docker.io and start dockerd"
    return True, f"engine {version}"
