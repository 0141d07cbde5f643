"""The use-case matrix: every location combination of the three use-case Skills (thesis Figure 5.3, Table 5.2).

Each Skill of the catalog (People Detection, Autonomous Navigation, Autonomous Mapping) runs as
its real ROS nodes (``bridgeos-usecase``) once per location combination its config allows:
every ``either`` component on the robot or in the cloud, the fixed ones where they must be.

    host (the robot)                                      netns (the cloud)
    rosmaster, simulated robot                            cloud components, on CPU 1
    robot components in a cgroup: --robot-cpu of CPU 0 ── shaped link (benchmarks/_netshape.py, --preset)

The robot's components run in a cgroup whose CPU is capped (``--robot-cpu`` cores, default 0.5:
a robot's embedded CPU against a cloud core), so the cgroup's accounting gives the robot's CPU
and its processes the robot's RAM. The robot's network is what its components exchange over
loopback plus everything crossing the shaped link; its power is thesis eq. 4.1 (shares of CPU,
RAM and radio times their hourly consumption, constants below). Performance per Skill:

    people detection  median pointcloud-to-detection latency  (lower is better)
    navigation        seconds per navigation goal reached     (lower is better)
    mapping           laser scans folded into the map per s   (higher is better)

Per Skill the best combination is the one with the lowest estimated power among those whose
performance is at most 10 % worse than all on the robot and whose messages arrive (loss under
5 %); its changes against all on the robot are the Table 5.2 equivalent. Needs root (network
namespaces, tc, cgroups) and ROS 1, or with ``--ros 2`` the Skills' ROS 2 twins (``*_ros2`` samples,
rclpy nodes from the agent's venv): a Fast DDS discovery server on the robot stands in for the master,
every node finds the others through it (unicast only, across the shaped link) over UDP.

    .venv/bin/python benchmarks/usecases.py --quick   # all-robot and all-cloud per Skill, short windows
    .venv/bin/python benchmarks/usecases.py           # every combination (16), 30 s windows
    .venv/bin/python benchmarks/usecases.py --quick --ros 2

The last line is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
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
import tempfile
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _netshape
from _common import ROOT, free_port, log

from bridgeos_agent.ros2graph import discovery_server_command, rclpy_missing
from bridgeos_agent.skillconfig import SkillConfig, load_sample_skill_config

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
PERFORMANCE_SLACK = 0.10  # a best combination may be this much slower than all on the robot
MAX_LOSS_PCT = 5.0


@dataclass(frozen=True)
class SkillRun:
    """How one Skill is run and judged in the matrix."""

    sample: str  # catalog sample file (bridgeos_agent/samples)
    performance: str  # what the performance figure is, for the table
    higher_is_better: bool
    extra_args: dict[str, list[str]] = field(default_factory=dict)  # component -> arguments appended


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
        assert self.popen.stdout is not None
        for raw in self.popen.stdout:
            self.lines.append((time.monotonic(), raw.decode(errors="replace").rstrip()))

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

    @property
    def label(self) -> str:
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
        return int((self.acct / "cpuacct.usage").read_text()) / 1e9

    def rss_mib(self) -> float:
        total = 0
        for pid in (self.cpu / "cgroup.procs").read_text().split():
            with contextlib.suppress(OSError, IndexError, ValueError):
                total += int(Path(f"/proc/{pid}/statm").read_text().split()[1]) * PAGE
        return total / 2**20

    def remove(self) -> None:
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
        self.ros, self.domain_id = ros, domain_id
        self.processes: dict[str, Process] = {}
        self.master_uri = f"http://{link.host_ip}:{free_port()}"
        self.discovery = f"{link.host_ip}:{free_port()}"
        self.started = 0.0

    def env(self, location: str, component: str) -> dict[str, str]:
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
            env["PYTHONPATH"] = os.environ["PYTHONPATH"]  # a worktree's nodes, when run from one
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
        popen = subprocess.Popen(
            command, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, start_new_session=True
        )
        process = Process(name, popen)
        threading.Thread(target=process.read, name=f"read-{name}", daemon=True).start()
        self.processes[name] = process

    def start(self) -> None:
        if self.ros == 2:
            self.start_discovery_server()
        else:
            self.start_master()
        self.started = time.monotonic()
        for component, spec in self.config.components.items():
            location = self.where[component]
            container = spec.robot if location == "robot" else spec.cloud
            assert container is not None, f"{component} has no {location} container"
            program = {"bridgeos-usecase": [USECASE], "bridgeos-usecase2": USECASE2}
            command = [piece for part in container.command for piece in program.get(part, [part])]
            command += SKILLS[self.skill].extra_args.get(component, [])
            if component in HARDWARE:
                pass
            elif location == "robot":
                command = self.cgroup.wrap(command)
            else:
                command = [*self.link.exec_prefix, "taskset", "-c", "1", *command]
            self.spawn(component, command, self.env(location, component))

    def start_master(self) -> None:
        port = self.master_uri.rsplit(":", 1)[1]
        self.spawn("rosmaster", [ROS_PYTHON, "/usr/bin/rosmaster", "--core", "-p", port], self.env("robot", "master"))
        deadline = time.monotonic() + 20
        while not _answers(self.link.host_ip, int(port)):
            if time.monotonic() > deadline:
                raise RuntimeError(f"rosmaster did not answer: {self.tail('rosmaster')}")
            time.sleep(0.05)

    def start_discovery_server(self) -> None:
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
        return "\n".join(line for _, line in self.processes[name].lines[-lines:])

    def check_alive(self) -> None:
        for name, process in self.processes.items():
            if process.popen.poll() is not None:
                raise RuntimeError(f"{name} exited with {process.popen.returncode}:\n{self.tail(name)}")

    def stop(self) -> None:
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
        if self.skill == "people_detection":
            return [(t, v) for t, v, _ in self.processes["detector"].metrics("pointcloud_processing_ms")]
        if self.skill == "navigation":
            return [(t, 1.0) for t, line in list(self.processes["mover"].lines) if REACHED.match(line)]
        return [(t, v) for t, v, _ in self.processes["mapping"].metrics("scans_mapped") if v > 0]

    def performance(self, begin: float, end: float) -> float | None:
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
    import socket

    with contextlib.suppress(OSError), socket.create_connection((host, port), timeout=0.5):
        return True
    return False


def measure(
    run: Run, warmup: float, window: float, link_mbit: float, robot_cores: float, patience: float
) -> Measurement:
    """Start the run, wait for its first result and the warm-up, then measure the window."""
    run.start()
    deadline = time.monotonic() + patience
    while run.first_output() is None and run.skill != "navigation":
        run.check_alive()
        if time.monotonic() > deadline:
            raise RuntimeError(f"{run.skill}: no result in {patience:.0f} s")
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
    # Navigation's result is a goal reached: its window lasts until it holds one.
    while time.monotonic() - begin < window or (run.first_output() is None and time.monotonic() < deadline):
        time.sleep(min(0.5, max(0.05, window - (time.monotonic() - begin))))
        rss.append(run.cgroup.rss_mib())
    end = time.monotonic()
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
    )


def change_pct(value: float | None, base: float | None, higher_is_better: bool = True) -> float | None:
    """Return the change from the base in percent; for performance, positive means better."""
    if value is None or base is None or base == 0:
        return None
    if higher_is_better:
        return 100 * (value - base) / base
    return 100 * (base / value - 1) if value else None


def best_of(rows: list[Measurement], higher_is_better: bool) -> Measurement:
    """Return the lowest-power combination that keeps performance within the slack, arriving messages."""
    base = rows[0]
    fine = []
    for row in rows:
        change = change_pct(row.performance, base.performance, higher_is_better)
        if change is not None and change >= -100 * PERFORMANCE_SLACK and row.loss_pct <= MAX_LOSS_PCT:
            fine.append(row)
    return min(fine or [base], key=lambda r: r.power_w)


def table(skill: str, rows: list[Measurement]) -> str:
    """Return one Skill's combinations as a markdown table (thesis Figure 5.3's rows)."""
    best = best_of(rows, SKILLS[skill].higher_is_better)
    lines = [
        f"### {skill.replace('_', ' ')}: performance is {SKILLS[skill].performance}",
        "",
        "| combination | performance | robot CPU % | robot RAM MiB | robot network kB/s | radio kB/s "
        "| power W (eq. 4.1) | loss % | first result s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        perf = f"{row.performance:.3g}" if row.performance is not None else "—"
        init = f"{row.init_s:.2f}" if row.init_s is not None else "—"
        label = f"**{row.label}** (best)" if row is best else row.label
        lines.append(
            f"| {label} | {perf} | {row.cpu_pct:.1f} | {row.ram_mib:.1f} | {row.network_kbps:.1f} "
            f"| {row.radio_kbps:.1f} | {row.power_w:.2f} | {row.loss_pct:.2f} | {init} |"
        )
    return "\n".join(lines)


@contextlib.contextmanager
def robot_and_cloud(preset: str, robot_cores: float) -> Iterator[tuple[_netshape.Link, RobotCgroup]]:
    _netshape.clean()
    link = _netshape.Link(_netshape.conditions_for(preset)).up()
    cgroup = RobotCgroup(robot_cores)
    try:
        yield link, cgroup
    finally:
        link.down()
        cgroup.remove()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="all-robot and all-cloud only, short windows")
    parser.add_argument("--preset", default="wifi", choices=sorted(_netshape.PRESETS), help="the robot-cloud link")
    parser.add_argument("--robot-cpu", type=float, default=0.5, help="cores the robot's components get (0.1-2)")
    parser.add_argument("--window", type=float, default=None, help="seconds measured per combination")
    parser.add_argument("--warmup", type=float, default=None, help="seconds after the first result before measuring")
    parser.add_argument("--skills", default=",".join(SKILLS), help="comma-separated Skills to run")
    parser.add_argument("--ros", type=int, default=1, choices=(1, 2), help="run the Skills' ROS 1 or ROS 2 nodes")
    parser.add_argument(
        "--ros-domain", type=int, default=int(os.environ.get("ROS_DOMAIN_ID") or 0), help="ROS_DOMAIN_ID (--ros 2)"
    )
    parser.add_argument("--out", type=Path, default=ROOT / ".data" / "bench" / "usecases.md", help="matrix table")
    args = parser.parse_args(argv)
    skills = [s for s in args.skills.split(",") if s]
    unknown = set(skills) - set(SKILLS)
    if unknown or not skills:
        parser.error(f"--skills takes {', '.join(SKILLS)}, not {', '.join(sorted(unknown)) or 'nothing'}")
    if not 0.1 <= args.robot_cpu <= 2:
        parser.error("--robot-cpu is between 0.1 and 2 cores")
    if os.geteuid() != 0:
        parser.error("needs root: network namespaces, tc and cgroups")
    if args.ros == 1 and (not Path("/usr/bin/rosmaster").exists() or not Path(USECASE).exists()):
        parser.error("needs ROS 1 (scripts/services.sh ros) and the agent installed (make install)")
    if args.ros == 2 and rclpy_missing():
        parser.error(f"--ros 2 needs rclpy: {rclpy_missing()}")
    if not 0 <= args.ros_domain <= 232:
        parser.error("--ros-domain is 0-232")
    window = args.window or (3.0 if args.quick else 30.0)
    warmup = args.warmup if args.warmup is not None else (1.0 if args.quick else 8.0)
    conditions = _netshape.conditions_for(args.preset)
    link_mbit = conditions.up_mbit + conditions.down_mbit
    log(
        f"ROS {args.ros}, link {args.preset} ({conditions.as_dict()}), robot CPU {args.robot_cpu} core, "
        f"window {window:.0f} s, warm-up {warmup:.1f} s"
    )

    results: dict[str, list[Measurement]] = {}
    tables = [
        f"ROS {args.ros}. Link `{args.preset}` {conditions.as_dict()}; robot CPU {args.robot_cpu} core; "
        f"window {window:.0f} s; "
        f"power constants (W at full use) {ENERGY_W}, robot RAM {ROBOT_RAM_MIB:.0f} MiB."
    ]
    with robot_and_cloud(args.preset, args.robot_cpu) as (link, cgroup), tempfile.TemporaryDirectory() as tmp:
        for skill in skills:
            config = load_sample_skill_config(SKILLS[skill].sample + ("_ros2" if args.ros == 2 else ""))
            combos = placements(config)
            if args.quick:
                combos = [combos[0], combos[-1]]
            results[skill] = []
            for index, where in enumerate(combos, 1):
                run = Run(skill, config, where, link, cgroup, Path(tmp), args.ros, args.ros_domain)
                log(f"{skill} {index}/{len(combos)}: " + ", ".join(f"{c}@{w}" for c, w in where.items()))
                try:
                    row = measure(run, warmup, window, link_mbit, args.robot_cpu, patience=60)
                finally:
                    run.stop()
                results[skill].append(row)
            tables.append(table(skill, results[skill]))
            log("\n" + tables[-1])

    figures: dict[str, object] = {
        "preset": args.preset,
        "robot_cpu": args.robot_cpu,
        "combinations": 0,
        "ros": args.ros,
    }
    losses, inits = [], []
    for skill, rows in results.items():
        figures["combinations"] = int(figures["combinations"]) + len(rows)  # type: ignore[call-overload]
        losses += [row.loss_pct for row in rows]
        inits += [row.init_s for row in rows if row.init_s is not None and skill != "navigation"]
        higher = SKILLS[skill].higher_is_better
        best, base = best_of(rows, higher), rows[0]
        figures[f"{skill}_best"] = best.label
        figures[f"{skill}_performance_pct"] = _round(change_pct(best.performance, base.performance, higher))
        for key, attr in (("cpu", "cpu_pct"), ("ram", "ram_mib"), ("network", "network_kbps"), ("power", "power_w")):
            figures[f"{skill}_{key}_pct"] = _round(change_pct(getattr(best, attr), getattr(base, attr)))
    figures["delivery_ratio"] = round(1 - statistics.fmean(losses) / 100, 4) if losses else None
    figures["skill_init_s"] = round(statistics.median(inits), 2) if inits else None
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n\n".join(tables) + "\n")
    log(f"matrix written to {args.out}")
    print(json.dumps(figures))
    return 0


def _round(value: float | None) -> float | None:
    return round(value, 2) if value is not None else None


if __name__ == "__main__":
    sys.exit(main())
