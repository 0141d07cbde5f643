"""usecases.py's runs: one Skill's real ROS nodes in one location combination, on a capped robot and a shaped link."""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import shutil
import signal
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import _netshape
from _common import free_port

from bridgeos_agent.ros2graph import discovery_server_command
from bridgeos_agent.rosnames import instance_namespace
from bridgeos_agent.skillconfig import SkillConfig

ROS_PYTHON = "/usr/bin/python3"
USECASE = shutil.which("bridgeos-usecase") or str(Path(sys.executable).parent / "bridgeos-usecase")
# The ROS 2 nodes run in this venv's Python: its script when installed, else the module.
_USECASE2 = Path(sys.executable).parent / "bridgeos-usecase2"
USECASE2 = [str(_USECASE2)] if _USECASE2.exists() else [sys.executable, "-m", "bridgeos_agent.usecases.ros2"]
HARDWARE = {"sim"}  # the simulated robot stands in for drivers and motors: not a Skill's workload
CGROUP = f"bosuc-robot-{os.getpid()}"  # one per run: two runs never share a cap or its accounting
PAGE = os.sysconf("SC_PAGE_SIZE")
METRIC = re.compile(r"^\[(?P<node>[\w-]+)\] metric (?P<name>\w+)=(?P<value>\S+)(?P<labels>.*)$")
REACHED = re.compile(r"^\[mover\] reached goal")

# Thesis eq. 4.1 constants for the benchmark's robot: Ec (W at full use) and capacities.
ENERGY_W = {"cpu": 10.0, "ram": 3.0, "radio": 2.5}
ROBOT_RAM_MIB = 2048.0
BIG_CLOUD_RATE = 0.2  # clouds a second with --cloud-mb: one every 5 s (a 35 MB cloud takes 7 s over wifi)

# The Skill Router of the thesis-sized run, in a process of its own (the robot's middleware, so in
# the robot's cgroup): the people detection sample's routes, each component active where it runs.
ROUTER = """
import asyncio, json, logging, signal, sys
from bridgeos_agent.router import RouterSettings, SkillRouter
from bridgeos_agent.skillconfig import load_sample_skill_config

logging.basicConfig(level=logging.INFO, format="[router] %(message)s", stream=sys.stdout)

async def main(master, host, sample, where):
    settings = RouterSettings(ros_host=host, http_host="127.0.0.1", statistics_period=2.0)
    router = SkillRouter(load_sample_skill_config(sample), ros_master=master, settings=settings)
    for component, location in json.loads(where).items():
        router.set_active(component, location)
    await router.start()
    print("[router] routing", flush=True)
    stop = asyncio.Event()
    asyncio.get_running_loop().add_signal_handler(signal.SIGTERM, stop.set)
    while not stop.is_set():
        try:
            await asyncio.wait_for(stop.wait(), 2.0)
        except asyncio.TimeoutError:
            pass
        for name, stats in router.statistics().items():
            if stats.get("kind") == "topic":
                print(f"[router] metric relay_dropped={stats['dropped']} topic={name}", flush=True)
                print(f"[router] metric relay_delivered={stats['delivered']} topic={name}", flush=True)
    await router.close()

asyncio.run(main(*sys.argv[1:5]))
"""


@dataclass(frozen=True)
class SkillRun:
    """How one Skill is run and judged in the matrix."""

    sample: str  # catalog sample file (bridgeos_agent/samples)
    performance: str  # what the performance figure is, for the table
    higher_is_better: bool
    extra_args: dict[str, list[str]] = field(default_factory=dict)  # component -> arguments appended
    routed: bool = False  # components in their instance namespaces, topics relayed by a Skill Router


def big_cloud_run(megabytes: float, rate: float) -> SkillRun:
    """Return people detection publishing thesis-sized clouds, relayed by the Skill Router."""
    return SkillRun(
        "people_detection",
        f"{megabytes:g} MB pointcloud→detection ms (median)",
        False,
        {"pointcloud": ["--megabytes", f"{megabytes:g}", "--rate", f"{rate:g}"]},
        routed=True,
    )


SKILLS = {
    "people_detection": SkillRun(
        "people_detection", "pointcloud→detection ms (median)", False, {"pointcloud": ["--rate", "2"]}
    ),
    "navigation": SkillRun("navigation", "s per goal", False, {"sim": ["--speed", "2.0"]}),
    "mapping": SkillRun("mapping", "scans mapped / s", True, {"mapping": ["--report-period", "1"]}),
}


@dataclass
class Process:
    """One running node and what it printed."""

    name: str
    popen: subprocess.Popen[bytes]
    lines: list[tuple[float, str]] = field(default_factory=list)

    def read(self) -> None:
        """Collect the process's output lines with the time each arrived, until it closes."""
        assert self.popen.stdout is not None
        for raw in self.popen.stdout:
            self.lines.append((time.monotonic(), raw.decode(errors="replace").rstrip()))

    def peak_rss_mib(self) -> float | None:
        """Return the process's peak resident memory so far (VmHWM), or None once it is gone."""
        with contextlib.suppress(OSError, ValueError):
            for line in Path(f"/proc/{self.popen.pid}/status").read_text().splitlines():
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024
        return None

    def metrics(self, name: str) -> list[tuple[float, float, str]]:
        """Return (time, value, labels) of every report of a metric."""
        found = []
        for t, line in list(self.lines):
            match = METRIC.match(line)
            if match and match["name"] == name:
                with contextlib.suppress(ValueError):
                    found.append((t, float(match["value"]), match["labels"].strip()))
        return found


@dataclass
class Measurement:
    """What one location combination measured on the robot."""

    skill: str
    placement: dict[str, str]
    performance: float | None
    cpu_pct: float  # of one core
    ram_mib: float
    network_kbps: float  # kB/s the robot's components exchanged (loopback + radio)
    radio_kbps: float
    power_w: float
    loss_pct: float
    init_s: float | None
    results: int = 0  # Skill results in the window (detections, goals, map reports)
    peak_rss_mib: dict[str, float] = field(default_factory=dict)  # per process, thesis-sized run only
    relay_dropped: int = 0  # messages the Skill Router dropped for slow subscribers (routed runs)
    relay_delivered: int = 0  # messages it delivered to subscribers

    @property
    def relay_loss_pct(self) -> float:
        """Return the share of the router's deliveries it dropped (a subscriber behind the link)."""
        total = self.relay_dropped + self.relay_delivered
        return 100 * self.relay_dropped / total if total else 0.0

    @property
    def label(self) -> str:
        """Name the combination by the components it moved to the cloud."""
        moved = [c for c, where in self.placement.items() if where == "cloud"]
        return "cloud: " + ", ".join(moved) if moved else "all on robot"


class RobotCgroup:
    """A cgroup (v1 cpu + cpuacct) capping and accounting the robot's components."""

    def __init__(self, cores: float) -> None:
        self.cpu = Path("/sys/fs/cgroup/cpu") / CGROUP
        self.acct = Path("/sys/fs/cgroup/cpuacct") / CGROUP
        for path in (self.cpu, self.acct):
            path.mkdir(exist_ok=True)
        period = 100_000
        (self.cpu / "cpu.cfs_period_us").write_text(str(period))
        (self.cpu / "cpu.cfs_quota_us").write_text(str(int(cores * period)))

    def wrap(self, command: list[str]) -> list[str]:
        """Return a command that joins the cgroup, pinned to CPU 0, before it runs."""
        join = 'echo $$ > "$1"; echo $$ > "$2"; shift 2; exec "$@"'
        return [
            "taskset",
            "-c",
            "0",
            "sh",
            "-c",
            join,
            "sh",
            str(self.cpu / "cgroup.procs"),
            str(self.acct / "cgroup.procs"),
            *command,
        ]

    def cpu_seconds(self) -> float:
        """Return the CPU time the robot's components used so far."""
        return int((self.acct / "cpuacct.usage").read_text()) / 1e9

    def rss_mib(self) -> float:
        """Return the resident memory of the robot's components now."""
        total = 0
        for pid in (self.cpu / "cgroup.procs").read_text().split():
            with contextlib.suppress(OSError, IndexError, ValueError):
                total += int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * PAGE
        return total / 2**20

    def remove(self) -> None:
        """Remove the cgroup once its last process has exited."""
        for path in (self.cpu, self.acct):
            for _ in range(50):
                try:
                    path.rmdir()
                    break
                except FileNotFoundError:
                    break
                except OSError:
                    time.sleep(0.1)  # its last process is still exiting


def placements(config: SkillConfig) -> list[dict[str, str]]:
    """Return every location combination the config allows, all on the robot first."""
    movable = [c for c, spec in config.components.items() if spec.location == "either"]
    combos = []
    for choice in itertools.product(("robot", "cloud"), repeat=len(movable)):
        where = {c: (spec.location if spec.location != "either" else "robot") for c, spec in config.components.items()}
        where.update(zip(movable, choice, strict=True))
        combos.append(where)
    return combos


def interface_bytes(device: str, *counters: str) -> int:
    """Return the sum of a network device's byte counters."""
    return sum(int(Path(f"/sys/class/net/{device}/statistics/{c}").read_text()) for c in counters)


class Run:
    """One Skill in one location combination: a rosmaster, its nodes, and their output."""

    def __init__(
        self,
        skill: str,
        config: SkillConfig,
        where: dict[str, str],
        link: _netshape.Link,
        cgroup: RobotCgroup,
        home: Path,
        spec: SkillRun | None = None,
        ros: int = 1,
        domain_id: int = 0,
    ) -> None:
        self.skill, self.config, self.where, self.link, self.cgroup, self.home = (
            skill,
            config,
            where,
            link,
            cgroup,
            home,
        )
        self.spec = spec or SKILLS[skill]
        self.ros, self.domain_id = ros, domain_id
        self.processes: dict[str, Process] = {}
        self.master_uri = f"http://{link.host_ip}:{free_port()}"
        self.discovery = f"{link.host_ip}:{free_port()}"
        self.started = 0.0

    def env(self, location: str, component: str) -> dict[str, str]:
        """Return a node's environment at its location: its ROS master or DDS discovery, its namespace."""
        env = {
            "PATH": f"/usr/bin:/bin:/usr/sbin:/sbin:{Path(USECASE).parent}",
            "HOME": os.environ.get("HOME", "/root"),
            "LANG": "C.UTF-8",
            "PYTHONUNBUFFERED": "1",
            "ROS_MASTER_URI": self.master_uri,
            "ROS_IP": self.link.host_ip if location == "robot" else self.link.cloud_ip,
            "ROS_HOME": str(self.home),
            "BRIDGEOS_COMPONENT": component,
            "BRIDGEOS_LOCATION": location,
        }
        if os.environ.get("PYTHONPATH"):
            env["PYTHONPATH"] = os.environ["PYTHONPATH"]  # a worktree's agent, when the run uses one
        if self.spec.routed and component in self.config.components:
            env["ROS_NAMESPACE"] = instance_namespace(self.config.skill_id, component, location)  # type: ignore[arg-type]
        if self.ros == 2:
            env |= {
                "ROS_DOMAIN_ID": str(self.domain_id),
                "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
                "ROS_DISCOVERY_SERVER": self.discovery,
                "ROS_LOG_DIR": str(self.home / "ros2-logs"),
                # UDP only: shared memory would carry a "cloud" node's data around the shaped link.
                "FASTDDS_BUILTIN_TRANSPORTS": "UDPv4",
            }
        return env

    def spawn(self, name: str, command: list[str], env: dict[str, str]) -> None:
        """Start a node in a session of its own and read its output in a thread."""
        popen = subprocess.Popen(
            command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
        )
        process = Process(name, popen)
        threading.Thread(target=process.read, name=f"read-{name}", daemon=True).start()
        self.processes[name] = process

    def start(self) -> None:
        """Start the master (or discovery server), the router if routed, then every component where it runs."""
        if self.ros == 2:
            self.start_discovery_server()
        else:
            self.start_master()
        self.started = time.monotonic()
        if self.spec.routed:
            placement = json.dumps(self.where)
            router = [sys.executable, "-c", ROUTER, self.master_uri, self.link.host_ip, self.spec.sample, placement]
            self.spawn("router", self.cgroup.wrap(router), self.env("robot", "router"))
        for component, spec in self.config.components.items():
            location = self.where[component]
            container = spec.robot if location == "robot" else spec.cloud
            assert container is not None, f"{component} has no {location} container"
            program = {"bridgeos-usecase": [USECASE], "bridgeos-usecase2": USECASE2}
            command = [piece for part in container.command for piece in program.get(part, [part])]
            command += self.spec.extra_args.get(component, [])
            if component in HARDWARE:
                pass
            elif location == "robot":
                command = self.cgroup.wrap(command)
            else:
                command = [*self.link.exec_prefix, "taskset", "-c", "1", *command]
            self.spawn(component, command, self.env(location, component))

    def start_master(self) -> None:
        """Start the run's rosmaster on the robot and wait until it answers."""
        port = self.master_uri.rsplit(":", 1)[1]
        self.spawn("rosmaster", [ROS_PYTHON, "/usr/bin/rosmaster", "--core", "-p", port], self.env("robot", "master"))
        deadline = time.monotonic() + 20
        while not _answers(self.link.host_ip, int(port)):
            if time.monotonic() > deadline:
                raise RuntimeError(f"rosmaster did not answer: {self.tail('rosmaster')}")
            time.sleep(0.05)

    def start_discovery_server(self) -> None:
        """Start the Fast DDS discovery server on the robot and wait until it serves."""
        host, port = self.discovery.rsplit(":", 1)
        argv, extra = discovery_server_command(host, int(port))
        self.spawn("discovery", argv, {**self.env("robot", "discovery"), **extra})
        deadline = time.monotonic() + 20
        while not any("Server Addresses" in line for _, line in list(self.processes["discovery"].lines)):
            self.check_alive()
            if time.monotonic() > deadline:
                raise RuntimeError(f"the discovery server did not start: {self.tail('discovery')}")
            time.sleep(0.05)

    def tail(self, name: str, lines: int = 15) -> str:
        """Return a node's last output lines."""
        return "\n".join(line for _, line in self.processes[name].lines[-lines:])

    def check_alive(self) -> None:
        """Raise if a node exited, with its last output."""
        for name, process in self.processes.items():
            if process.popen.poll() is not None:
                raise RuntimeError(f"{name} exited with {process.popen.returncode}:\n{self.tail(name)}")

    def stop(self) -> None:
        """Stop every node: TERM to each session, KILL after 10 s."""
        for process in reversed(list(self.processes.values())):
            with contextlib.suppress(ProcessLookupError):
                os.killpg(process.popen.pid, signal.SIGTERM)
        for process in self.processes.values():
            try:
                process.popen.wait(timeout=10)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.popen.pid, signal.SIGKILL)
                process.popen.wait(timeout=10)

    # --- the Skill's performance, from what its nodes printed

    def first_output(self) -> float | None:
        """Return the time of the Skill's first result, or None before it."""
        times = [t for t, *_ in self._performance_events()]
        return min(times) if times else None

    def _performance_events(self) -> list[tuple[float, float]]:
        """Return the Skill's results so far as (time, value) pairs."""
        if self.skill == "people_detection":
            return [(t, v) for t, v, _ in self.processes["detector"].metrics("pointcloud_processing_ms")]
        if self.skill == "navigation":
            return [(t, 1.0) for t, line in list(self.processes["mover"].lines) if REACHED.match(line)]
        return [(t, v) for t, v, _ in self.processes["mapping"].metrics("scans_mapped") if v > 0]

    def performance(self, begin: float, end: float) -> float | None:
        """Return the Skill's performance figure over a window (None without results)."""
        events = self._performance_events()
        if self.skill == "people_detection":
            values = [v for t, v in events if begin <= t <= end]
            return statistics.median(values) if values else None
        if self.skill == "navigation":
            # Seconds per goal from the mover's start: its first goal's planning and path included.
            began = next(
                (t for t, line in list(self.processes["mover"].lines) if line.startswith("[mover] tour")), None
            )
            reached = [t for t, _ in events if t <= end]
            return (reached[-1] - began) / len(reached) if reached and began is not None else None
        inside = [(t, v) for t, v in events if begin <= t <= end]
        if len(inside) < 2:
            return None
        (t0, v0), (t1, v1) = inside[0], inside[-1]
        return (v1 - v0) / (t1 - t0)

    def loss_pct(self) -> float:
        """Return the mean of the last loss each node reported per topic."""
        last: dict[tuple[str, str], float] = {}
        for name, process in self.processes.items():
            for _, value, labels in process.metrics("message_loss_pct"):
                last[(name, labels)] = value
        return statistics.fmean(last.values()) if last else 0.0


def _answers(host: str, port: int) -> bool:
    """Tell whether something accepts TCP connections on host:port."""
    import socket

    with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=0.5):
        return True
    return False


def measure(
    run: Run,
    warmup: float,
    window: float,
    link_mbit: float,
    robot_cores: float,
    patience: float,
    min_results: int = 0,
) -> Measurement:
    """Start the run, wait for its first result and the warm-up, then measure the window.

    With ``min_results`` the window lasts until that many results came in it too (or patience ends).
    """
    run.start()
    deadline = time.monotonic() + patience
    while run.first_output() is None and run.skill != "navigation":
        run.check_alive()
        if time.monotonic() > deadline:
            tails = "\n".join(f"--- {name}\n{run.tail(name, 6)}" for name in run.processes if name != "rosmaster")
            raise RuntimeError(f"{run.skill}: no result in {patience:.0f} s\n{tails}")
        time.sleep(0.1)
    first = run.first_output()
    time.sleep(warmup)
    run.check_alive()
    lo0, radio0, cpu0, begin = (
        interface_bytes("lo", "tx_bytes"),
        interface_bytes(run.link.robot_device, "tx_bytes", "rx_bytes"),
        run.cgroup.cpu_seconds(),
        time.monotonic(),
    )
    rss = []
    enough_by = begin + window + patience  # how long a window waits for its min_results

    def results() -> int:
        return sum(1 for t, _ in run._performance_events() if t >= begin)

    # Navigation's result is a goal reached: its window lasts until it holds one.
    while (
        time.monotonic() - begin < window
        or (run.first_output() is None and time.monotonic() < deadline)
        or (results() < min_results and time.monotonic() < enough_by)
    ):
        time.sleep(min(0.5, max(0.05, window - (time.monotonic() - begin))))
        rss.append(run.cgroup.rss_mib())
        run.check_alive()
    end = time.monotonic()
    peaks = {name: peak for name, p in run.processes.items() if (peak := p.peak_rss_mib()) is not None}
    relayed = run.processes.get("router")
    relay = {
        name: int(sum({labels: v for _, v, labels in relayed.metrics(name)}.values())) if relayed else 0
        for name in ("relay_dropped", "relay_delivered")
    }
    seconds = end - begin
    lo1, radio1, cpu1 = (
        interface_bytes("lo", "tx_bytes"),
        interface_bytes(run.link.robot_device, "tx_bytes", "rx_bytes"),
        run.cgroup.cpu_seconds(),
    )
    run.check_alive()
    if first is None:
        first = run.first_output()
    cpu_share = (cpu1 - cpu0) / seconds
    ram = statistics.fmean(rss) if rss else 0.0
    radio_kbps = (radio1 - radio0) / seconds / 1000
    radio_share = min(1.0, radio_kbps * 8 / 1000 / link_mbit)
    # Thesis eq. 4.1 over the Skill's robot side: sum of each resource's share times its Ec.
    power = (
        ENERGY_W["cpu"] * min(1.0, cpu_share / robot_cores)
        + ENERGY_W["ram"] * min(1.0, ram / ROBOT_RAM_MIB)
        + ENERGY_W["radio"] * radio_share
    )
    return Measurement(
        skill=run.skill,
        placement=dict(run.where),
        performance=run.performance(begin, end),
        cpu_pct=100 * cpu_share,
        ram_mib=ram,
        network_kbps=(lo1 - lo0) / seconds / 1000 + radio_kbps,
        radio_kbps=radio_kbps,
        power_w=power,
        loss_pct=run.loss_pct(),
        init_s=(first - run.started) if first is not None else None,
        results=sum(1 for t, _ in run._performance_events() if begin <= t <= end),
        peak_rss_mib={k: v for k, v in peaks.items() if k != "rosmaster"},
        relay_dropped=relay["relay_dropped"],
        relay_delivered=relay["relay_delivered"],
    )


@contextlib.contextmanager
def robot_and_cloud(preset: str, robot_cores: float) -> Iterator[tuple[_netshape.Link, RobotCgroup]]:
    """Bring up the shaped link to the cloud's namespace and the robot's cgroup; take both down after."""
    _netshape.clean()
    link = _netshape.Link(_netshape.conditions_for(preset)).up()
    cgroup = RobotCgroup(robot_cores)
    try:
        yield link, cgroup
    finally:
        link.down()
        cgroup.remove()
