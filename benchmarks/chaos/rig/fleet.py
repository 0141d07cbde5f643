"""Real agents to break: one `bridgeos-agent run` in a process of its own, or a fleet of Robot Controllers in one.

An `Agent` is the agent's own command (`--simulate`, process runtime), optionally inside a
robot's network namespace, read through its Prometheus exporter and killed with -9 when asked. A
`Fleet` hosts many Robot Controllers in one process (`python -m benchmarks.chaos.rig fleet`) that
reports per robot what it sent, whether it is connected and what it still owes. The components
the agents start are found and ended through the process table.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import signal
import subprocess
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx
import psutil

from benchmarks._common import ROOT, free_port
from benchmarks.chaos.rig.base import BIN, PYTHON, kill_group, wait_until
from bridgeos_agent.runtime.cgroups import Cgroups
from tests.net.netns import _in_namespace

if TYPE_CHECKING:
    from benchmarks.chaos.rig.cloud import Cloud


class Agent:
    """The real agent (`bridgeos-agent run --simulate`), started at once, optionally inside a network namespace."""

    def __init__(
        self,
        robot: str,
        token: str,
        master: str,
        data_dir: Path,
        log_path: Path,
        *,
        namespace: str | None = None,
        sample_interval: float = 0.5,
        keep_components: bool = False,
        options: Sequence[str] = (),
    ) -> None:
        self.robot = robot
        self.namespace = namespace
        self.data_dir = data_dir
        self.log_path = log_path
        self.metrics_port = free_port()
        command = [str(BIN / "bridgeos-agent"), "run", "--master", master, "--robot", robot, "--token", token]
        command += ["--simulate", "--runtime", "process", "--data-dir", str(data_dir)]
        command += ["--sample-interval", str(sample_interval), "--metrics", f"127.0.0.1:{self.metrics_port}"]
        command += ["--allow-insecure"]
        # Kept, a killed or stopped agent's components run on for the next agent to re-adopt.
        command += [] if keep_components else ["--stop-components-on-exit"]
        command += options
        if namespace is not None:
            command = ["ip", "netns", "exec", namespace, *command]
        self.command = command
        self.process: subprocess.Popen[bytes]
        self.start()

    def start(self) -> None:
        """Start the agent (again, after a kill: every start appends to the same log)."""
        with self.log_path.open("ab") as out:
            self.process = subprocess.Popen(
                self.command,
                cwd=ROOT,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
                stdout=out,
                stderr=subprocess.STDOUT,
            )

    def alive(self) -> bool:
        return self.process.poll() is None

    def scrape(self) -> dict[str, float]:
        """Read the agent's exporter (from inside its namespace): {metric name: value summed over labels}."""

        def get() -> str:
            with httpx.Client(timeout=5) as client:
                return client.get(f"http://127.0.0.1:{self.metrics_port}/metrics").text

        text = _in_namespace(self.namespace, get) if self.namespace else get()
        values: dict[str, float] = Counter()
        for line in str(text).splitlines():
            match = re.match(r"^([a-zA-Z_:][\w:]*)(\{[^}]*\})? ([-+\deE.naif]+)$", line)
            if match:
                values[match.group(1)] += float(match.group(3))
        return dict(values)

    def try_scrape(self) -> dict[str, float] | None:
        try:
            return self.scrape()
        except (httpx.HTTPError, OSError):
            return None

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace")

    def kill(self) -> None:
        """kill -9 the agent process alone: the components it started run on in their own sessions."""
        if self.process.poll() is None:
            self.process.kill()
        self.process.wait(10)

    def stop(self, timeout: float = 30.0) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.kill()


def settled_points(agent: Agent, cloud: Cloud, robot: str, timeout: float = 60.0) -> tuple[dict[str, float], int, int]:
    """Return (the agent's figures, rows stored, duplicate rows) at a moment nothing was in flight.

    Nothing is owed (outbox empty, no unstored frame unacked, disk writable) at one scrape, the
    rows are counted, and a second scrape shows no point was sent in between: then every point the
    agent counts as sent was either stored or counted as dropped, and no later one was counted.
    """
    deadline = time.monotonic() + timeout
    while True:
        first = agent.try_scrape() or {}
        if _idle(first):
            stored, duplicated = cloud.metric_rows(robot)
            second = agent.try_scrape() or {}
            sent = "bridgeos_agent_metric_points_sent_total"
            if _idle(second) and second.get(sent) == first.get(sent):
                return first, stored, duplicated
        if time.monotonic() > deadline:
            raise TimeoutError(f"the agent never settled (nothing owed, nothing sent between two reads): {first}")
        time.sleep(0.05)


def _idle(stats: dict[str, float]) -> bool:
    return (
        stats.get("bridgeos_agent_link_up") == 1
        and stats.get("bridgeos_agent_outbox_frames") == 0
        and stats.get("bridgeos_agent_unstored_frames_in_flight", 0) == 0
        and stats.get("bridgeos_agent_outbox_disk_full", 0) == 0
    )


def _component_processes(robot: str, skill: str) -> list[tuple[psutil.Process, str, str]]:
    found = []
    for proc in psutil.process_iter(["pid"]):
        try:
            if proc.status() == psutil.STATUS_ZOMBIE:
                continue
            env = proc.environ()
        except psutil.Error:
            continue
        if env.get("BRIDGEOS_ROBOT") == robot and env.get("BRIDGEOS_SKILL") == skill and "BRIDGEOS_COMPONENT" in env:
            found.append((proc, env["BRIDGEOS_COMPONENT"], env.get("BRIDGEOS_LOCATION", "?")))
    return found


def instances(robot: str, skill: str) -> Counter[tuple[str, str]]:
    """Count the running processes of a Skill's components, per (component, location), robot and cloud copies."""
    return Counter((component, location) for _, component, location in _component_processes(robot, skill))


def kill_instances(robot: str, skill: str) -> int:
    """Kill every process of a Skill's components (cloud copies outlive their worker by design)."""
    found = _component_processes(robot, skill)
    for proc, _, _ in found:
        with contextlib.suppress(psutil.Error):
            proc.kill()
    psutil.wait_procs([proc for proc, _, _ in found], timeout=5)
    # Their control groups too: no runtime saw them end.
    Cgroups(robot).sweep(min_age_s=0)
    return len(found)


class Fleet:
    """Several real Robot Controllers in one process, reporting what each sent, owes and whether it is connected."""

    def __init__(self, master: str, robots: list[tuple[str, str]], workdir: Path, *, sample_interval: float = 0.2):
        self.workdir = workdir
        self.status_path = workdir / "fleet-status.json"
        self.spec = {
            "master": master,
            "robots": robots,
            "data_dir": str(workdir / "agents"),
            "status": str(self.status_path),
            "sample_interval": sample_interval,
        }
        (workdir / "fleet.json").write_text(json.dumps(self.spec))
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        with (self.workdir / "fleet.log").open("ab") as out:
            self.process = subprocess.Popen(
                [PYTHON, "-m", "benchmarks.chaos.rig", "fleet", str(self.workdir / "fleet.json")],
                cwd=ROOT,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def status(self) -> dict[str, dict[str, Any]]:
        """Return per robot: sent (metric points), owed (frames not acked), connected, connected_at (wall time)."""
        if self.process is not None and self.process.poll() is not None and self.process.returncode not in (0, -15):
            raise RuntimeError(f"the fleet exited with {self.process.returncode}:\n{self.log_tail()}")
        try:
            return json.loads(self.status_path.read_text())
        except (OSError, ValueError):
            return {}

    def all_connected(self, since: float = 0.0) -> bool:
        status = self.status()
        return len(status) == len(self.spec["robots"]) and all(
            s["connected"] and s["connected_at"] > since for s in status.values()
        )

    def wait_connected(self, *, since: float = 0.0, timeout: float = 60.0) -> float:
        """Wait until every robot is connected on a connection made after ``since``; return the last one's time."""
        wait_until(lambda: self.all_connected(since), "every robot connected", timeout)
        return max(s["connected_at"] for s in self.status().values())

    def quiesce(self) -> None:
        """Stop making new metrics (the robots stay connected and keep delivering what they owe)."""
        assert self.process is not None
        self.process.send_signal(signal.SIGUSR1)
        wait_until(lambda: all(s.get("quiet") for s in self.status().values()), "fleet quiet", 10)

    def wait_delivered(self, timeout: float = 60.0) -> None:
        """Wait until no robot owes the cloud a frame."""
        wait_until(
            lambda: all(s["owed"] == 0 and s["connected"] for s in self.status().values()),
            "every robot's backlog acked",
            timeout,
        )

    def sent(self) -> int:
        return sum(s["sent"] for s in self.status().values())

    def owed(self) -> int:
        return sum(s["owed"] for s in self.status().values())

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            kill_group(self.process, signal.SIGTERM)
            kill_group(self.process)

    def log_tail(self, chars: int = 3000) -> str:
        path = self.workdir / "fleet.log"
        return path.read_text(errors="replace")[-chars:] if path.exists() else ""


async def host_fleet(spec: dict[str, Any]) -> None:
    """Run one Robot Controller per robot of the spec until SIGTERM, writing their status every 50 ms."""
    from bridgeos_agent.agent import settings_from_args
    from bridgeos_agent.cli import build_parser
    from bridgeos_agent.controller import RobotController

    parser = build_parser()
    controllers: dict[str, RobotController] = {}
    for robot, token in spec["robots"]:
        args = parser.parse_args(
            [
                *("run", "--master", spec["master"], "--robot", robot, "--token", token),
                *("--simulate", "--firewall", "off", "--sample-interval", str(spec["sample_interval"])),
                *("--data-dir", str(Path(spec["data_dir"]) / robot)),
            ]
        )
        controllers[robot] = RobotController(settings_from_args(args), plugins={})
    loop = asyncio.get_running_loop()
    stopping = asyncio.Event()
    quiet = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, stopping.set)
    loop.add_signal_handler(signal.SIGUSR1, quiet.set)
    runs = [loop.create_task(c.run(), name=f"agent {robot}") for robot, c in controllers.items()]
    connected_at = dict.fromkeys(controllers, 0.0)
    was_connected = dict.fromkeys(controllers, False)
    status_path = Path(spec["status"])
    quieted = False
    while not stopping.is_set():
        if quiet.is_set() and not quieted:
            # The resource monitor is the only source of metrics: without it a robot only delivers what it owes.
            for task in asyncio.all_tasks():
                if task.get_name() == "monitor":
                    task.cancel()
            quieted = True
        now = time.time()
        status = {}
        for robot, controller in controllers.items():
            connected = controller.connected.is_set()
            if connected and not was_connected[robot]:
                connected_at[robot] = now
            was_connected[robot] = connected
            status[robot] = {
                "sent": controller.metric_points_sent,
                "owed": len(controller.outbox),
                "connected": connected,
                "connected_at": connected_at[robot],
                "quiet": quieted,
            }
        temp = status_path.with_suffix(".tmp")
        temp.write_text(json.dumps(status))
        temp.replace(status_path)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stopping.wait(), 0.05)
    for controller in controllers.values():
        controller.stop()
    await asyncio.gather(*runs, return_exceptions=True)
