"""Process glue of `bridgeos-agent run` and `bridgeos-agent doctor`: logging, signals, checks."""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import shutil
import signal
import sys
import time
from pathlib import Path

import psutil
import websockets

from bridgeos_agent import __version__, protocol
from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.monitor import SimulatedRobot
from bridgeos_agent.protocol import Event
from bridgeos_agent.rosmaster import find_ros_master

__all__ = ["doctor", "run_agent", "settings_from_args"]

EXIT_REFUSED = 3


def settings_from_args(args: argparse.Namespace) -> AgentSettings:
    """Turn checked command-line options into the controller's settings."""
    data_dir = args.data_dir or Path.home() / ".local" / "share" / "bridgeos-agent" / args.robot
    simulated = None
    if args.simulate:
        simulated = SimulatedRobot(cpu=args.sim_cpu, ram=args.sim_ram, bandwidth=args.sim_bandwidth)
    return AgentSettings(
        master=args.master,
        robot=args.robot,
        token=args.token,
        data_dir=Path(data_dir),
        runtime=args.runtime,
        simulate=args.simulate,
        simulated=simulated,
        sample_interval=args.sample_interval,
        stop_components_on_exit=args.stop_components_on_exit,
    )


def run_agent(args: argparse.Namespace) -> int:
    """Run the Robot Controller until SIGINT/SIGTERM, a shutdown order or a refused token."""
    logging.basicConfig(
        level=logging.WARNING if args.quiet else logging.INFO,
        format="%(asctime)s %(message)s",
        datefmt="%H:%M:%S",
        stream=sys.stderr,
    )
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
        return await controller.run()

    return asyncio.run(main())


def doctor(args: argparse.Namespace) -> int:
    """Print one line per check with how to fix what fails; exit 0 when the agent can run."""
    results: list[tuple[bool, bool, str]] = []  # (ok, essential, line)

    def check(ok: bool, essential: bool, good: str, bad: str) -> None:
        results.append((ok, essential, good if ok else bad))
        print(f"{'ok  ' if ok else 'FAIL' if essential else 'warn'}  {good if ok else bad}")

    reachable, refused = asyncio.run(_probe_cloud(args.master, args.robot, args.token))
    check(
        reachable is True,
        True,
        f"cloud reachable at {args.master}",
        f"cannot reach the cloud at {args.master}: {reachable}. Check the URL and that the cloud runs.",
    )
    if reachable is True:
        check(
            refused is None,
            True,
            f"robot {args.robot} is accepted with this token",
            f"the cloud refused robot {args.robot}: {refused}. Ask the operator for the robot's token "
            "(python manage.py create_robot, or rotate it in the admin).",
        )
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


async def _probe_cloud(master: str, robot: str, token: str) -> tuple[bool | str, str | None]:
    """Connect and authenticate once; return (True or why unreachable, refusal reason or None)."""
    url = master.rstrip("/") + "/ws/robot/"
    try:
        async with websockets.connect(url, open_timeout=5, compression=None) as ws:
            request = protocol.make(Event.AUTHENTICATION_ROBOT, {"robot": robot, "token": token}, now=time.time())
            await ws.send(protocol.encode(request))
            answer = protocol.decode(await asyncio.wait_for(ws.recv(), 5))
    except (OSError, TimeoutError, websockets.WebSocketException, protocol.ProtocolError) as exc:
        return (str(exc) or type(exc).__name__), None
    if answer.event == Event.AUTHENTICATION_SUCCESS:
        return True, None
    return True, getattr(protocol.parse_payload(answer), "reason", answer.event)


def _docker_status() -> tuple[bool, str]:
    try:
        import docker
    except ImportError:
        return False, "the docker Python package is missing: pip install docker"
    try:
        client = docker.from_env(timeout=3)
        version = client.version().get("Version", "?")
        client.close()
    except Exception as exc:
        socket = os.environ.get("DOCKER_HOST", "/var/run/docker.sock")
        return False, f"no Docker engine at {socket} ({type(exc).__name__}); install docker.io and start dockerd"
    return True, f"engine {version}"
