"""Skill startup on the robot agent (thesis Figures 5.6-5.7).

Starts 1..N one-component Skills through the Robot Controller - sequentially, then all at
once - with the process runtime and with the Docker runtime, and prints the init time per
Skill beside the thesis's (5.26 +- 0.61 s sequential, 2.19 +- 0.33 s parallel, measured with
a manager and a router container per Skill). It then keeps adding Skills until the goal
count runs (1000 with processes, 300 with Docker on our 2-core machine; the thesis ran 110
at startup and 150 sequentially), reports the agent's memory per extra Skill (thesis: ~20 MB
manager + ~46 MB router; goal <=2 MB) and times a bare `docker run -d` of the same image in
the same run, with the network, init, log rotation and limits the runtime gives a component
(goal: Docker runtime <=1.1x bare).

The controller runs in this process with a simulated robot and no cloud reachable: what a
Skill start costs on the robot (allocation, launch, status frames written to the outbox),
not the network.

    .venv/bin/python benchmarks/skills_startup.py --quick
    .venv/bin/python benchmarks/skills_startup.py            # 1000 process / 300 docker skills
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import log
from _harness import arguments, report

from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.monitor import SimulatedRobot
from bridgeos_agent.robotconfig import parse_robot_config
from bridgeos_agent.skillconfig import parse_skill_config

IMAGE = "bridgeos/base:bookworm"
# Limits the runtime turns into the container's CPU and memory limits, and the bare run gets too.
RESOURCES = {"cpu": 0.1, "ram": 64}
THESIS = {"seq_init_s": (5.26, 0.61), "parallel_init_s": (2.19, 0.33)}
GOALS = {"process": 1000, "docker": 300}
WARM_UP = 9999  # the number of the Skill started once before the timed ones


def skill(n: int, runtime: str):
    """Return a one-component Skill that sleeps, for the given runtime."""
    spec = {"image": IMAGE, "command": ["sleep", "3600"]} if runtime == "docker" else {"command": ["sleep", "3600"]}
    worker = {"name": "Worker", "location": "robot", "ros": False, "resources": RESOURCES, "robot": spec}
    return parse_skill_config({"skill": f"Bench {n}", "skill_id": f"bench-{n:04d}", "components": {"worker": worker}})


def controller(runtime: str, data_dir: Path) -> RobotController:
    """Return a controller for a big simulated robot that never reaches a cloud."""
    settings = AgentSettings(
        master="ws://127.0.0.1:9",
        robot="bench-robot",
        token="unused",
        data_dir=data_dir,
        runtime=runtime,
        simulate=True,
        simulated=SimulatedRobot(cpu=10_000, ram=10_000_000, seed=1),
    )
    agent = RobotController(settings, say=lambda line: None)
    config = {"resources": {"cpu": 10_000, "ram": 10_000_000, "bandwidth": 10_000, "io": 10_000}}
    agent.apply_config(parse_robot_config(config), source="local")
    return agent


def rss_mib() -> float:
    """Return this process's resident memory now."""
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * resource.getpagesize() / 2**20


async def timed_start(agent: RobotController, n: int, runtime: str) -> float:
    started = time.perf_counter()
    record = await agent.start_skill(skill(n, runtime))
    if record.status != "running":
        raise RuntimeError(f"skill bench-{n:04d} did not start: {record.status}")
    return time.perf_counter() - started


async def measure(runtime: str, args: argparse.Namespace, data_dir: Path) -> dict:
    """Measure one runtime: sequential and parallel init, the most Skills run, memory per Skill."""
    agent = controller(runtime, data_dir)
    figures: dict = {}
    try:
        # One Skill first, not timed: the robot's network and the engine's caches are made once
        # per robot, as the bare runs' network is made before they are timed.
        await timed_start(agent, WARM_UP, runtime)
        await stop_all(agent)
        seq = []
        with BareRuns() if runtime == "docker" else contextlib.nullcontext() as bare:
            for n in range(args.seq):
                seq.append(await timed_start(agent, n, runtime))
                if bare is not None and n < args.bare:
                    await asyncio.to_thread(bare.run)
        figures["seq"] = seq
        figures["bare"] = bare.times if bare is not None else []
        log(f"{runtime}: {args.seq} skills one after another, {statistics.mean(seq):.3f} s each")
        await stop_all(agent)
        base = args.seq
        wall = time.perf_counter()
        parallel = await asyncio.gather(*(timed_start(agent, base + n, runtime) for n in range(args.parallel)))
        wall = time.perf_counter() - wall
        figures["parallel"] = list(parallel)
        figures["parallel_wall"] = wall
        log(
            f"{runtime}: {args.parallel} skills at once, {statistics.mean(parallel):.3f} s each "
            f"(all running after {wall:.2f} s)"
        )
        await stop_all(agent)
        # Keep adding Skills in batches until the goal runs or one fails.
        goal = args.max_process if runtime == "process" else args.max_docker
        before = rss_mib()
        running = 0
        batch = 50 if runtime == "process" else 10
        next_n = base + args.parallel
        wall = time.perf_counter()
        try:
            while running < goal:
                size = min(batch, goal - running)
                await asyncio.gather(*(timed_start(agent, next_n + n, runtime) for n in range(size)))
                next_n += size
                running += size
                if running % (batch * 4) == 0 or running == goal:
                    log(f"{runtime}: {running} skills running, agent RSS {rss_mib():.0f} MiB")
        except Exception as exc:
            log(f"{runtime}: stopped adding skills at {running}: {exc}")
        figures["max"] = running
        figures["max_wall"] = time.perf_counter() - wall
        figures["mb_per_skill"] = (rss_mib() - before) / running if running else None
        alive = sum(1 for record in agent.skills.values() if record.locations.get("worker") == "robot")
        figures["alive"] = alive
        await stop_all(agent)
    finally:
        await agent.runtime.close(stop_components=True)
        agent.outbox.close()
        if runtime == "docker":
            await asyncio.to_thread(
                subprocess.run, ["docker", "network", "rm", "bridgeos-bench-robot"], capture_output=True
            )
    return figures


async def stop_all(agent: RobotController) -> None:
    """Stop every Skill the benchmark started, 50 at a time."""
    ids = [skill_id for skill_id, record in agent.skills.items() if record.status == "running"]
    for chunk in range(0, len(ids), 50):
        await asyncio.gather(*(agent.stop_skill(skill_id) for skill_id in ids[chunk : chunk + 50]))
    agent.skills.clear()


class BareRuns:
    """Time `docker run -d` of the same image and command with what the runtime gives a component.

    The same as the docker runtime's container: a user-defined bridge network, an init process,
    host.docker.internal, the log rotation and the CPU and memory limits, so the ratio is the
    runtime's own cost, not the cost of what it sets up. Runs are taken one after each timed
    runtime start, so both see the machine alike.
    """

    network = "bridgeos-bench-bare"

    def __init__(self) -> None:
        self.names: list[str] = []
        self.times: list[float] = []

    def __enter__(self) -> BareRuns:
        subprocess.run(["docker", "network", "create", self.network], capture_output=True)
        self.run()  # the first, not timed: as the runtime's warm-up Skill
        self.times.clear()
        return self

    def run(self) -> float:
        name = f"bridgeos-bench-bare-{len(self.names)}"
        subprocess.run(["docker", "rm", "-f", name], capture_output=True)
        started = time.perf_counter()
        subprocess.run(
            [
                *("docker", "run", "-d", "--init", "--name", name, "--network", self.network),
                *("--add-host", "host.docker.internal:host-gateway", "--log-driver", "json-file"),
                *("--log-opt", "max-size=10485760", "--log-opt", "max-file=2"),
                *("--cpus", str(RESOURCES["cpu"]), "--memory", f"{RESOURCES['ram']}m"),
                *("--label", "io.bridgeos.bench=1", IMAGE, "sleep", "3600"),
            ],
            check=True,
            capture_output=True,
        )
        elapsed = time.perf_counter() - started
        self.times.append(elapsed)
        self.names.append(name)
        return elapsed

    def __exit__(self, *exc: object) -> None:
        subprocess.run(["docker", "rm", "-f", *self.names], capture_output=True)
        subprocess.run(["docker", "network", "rm", self.network], capture_output=True)


def docker_available() -> str | None:
    """Return why Docker cannot be measured, or None."""
    if shutil.which("docker") is None:
        return "no docker CLI"
    if subprocess.run(["docker", "image", "inspect", IMAGE], capture_output=True).returncode != 0:
        return f"no image {IMAGE} (run docker/build-images.sh)"
    return None


def main() -> int:
    parser = arguments(__doc__, "small counts, under a minute", whole_doc=True)
    parser.add_argument("--seq", type=int, default=10, help="skills started one after another")
    parser.add_argument("--parallel", type=int, default=20, help="skills started at once")
    parser.add_argument("--max-process", type=int, default=GOALS["process"], help="skills to run with processes")
    parser.add_argument("--max-docker", type=int, default=GOALS["docker"], help="skills to run with Docker")
    parser.add_argument(
        "--bare", type=int, default=10, help="bare docker runs, one after each of the first sequential starts"
    )
    parser.add_argument("--runtime", choices=("process", "docker", "both"), default="both")
    args = parser.parse_args()
    if args.quick:
        args.seq, args.parallel, args.max_process, args.max_docker, args.bare = 5, 10, 200, 20, 5
    if min(args.seq, args.parallel, args.max_process, args.max_docker, args.bare) < 1:
        parser.error("every count must be at least 1")
    runtimes = ["process", "docker"] if args.runtime == "both" else [args.runtime]
    why_not = docker_available()
    if "docker" in runtimes and why_not:
        log(f"docker runtime skipped: {why_not}")
        runtimes.remove("docker")
    results: dict[str, dict] = {}
    with tempfile.TemporaryDirectory(prefix="bridgeos-bench-skills-") as tmp:
        for runtime in runtimes:
            results[runtime] = asyncio.run(measure(runtime, args, Path(tmp) / runtime))
    bare = results.get("docker", {}).get("bare", [])

    def mean(values):
        return round(statistics.mean(values), 3) if values else None

    def sd(values):
        return round(statistics.stdev(values), 3) if values and len(values) > 1 else 0.0

    print()
    print("Skill startup, one component per skill, controller in-process, simulated robot (thesis Fig. 5.6-5.7)")
    for runtime, r in results.items():
        print(
            f"  {runtime:7s} init per skill: sequential {mean(r['seq'])} +- {sd(r['seq'])} s "
            f"(thesis {THESIS['seq_init_s'][0]} +- {THESIS['seq_init_s'][1]} s), "
            f"parallel x{args.parallel} {mean(r['parallel'])} +- {sd(r['parallel'])} s "
            f"(thesis {THESIS['parallel_init_s'][0]} +- {THESIS['parallel_init_s'][1]} s)"
        )
        goal = GOALS[runtime]
        asked = args.max_process if runtime == "process" else args.max_docker
        print(
            f"  {runtime:7s} skills running at once: {r['max']} (asked {asked}, "
            f"goal {goal}; thesis 110 at startup, 150 sequential), all up in {r['max_wall']:.1f} s; "
            f"agent memory per extra skill {r['mb_per_skill']:.3f} MB (goal <=2 MB; thesis ~66 MB)"
        )
    docker_over_bare = None
    if bare:
        paired = results["docker"]["seq"][: len(bare)]  # the starts each bare run followed
        docker_over_bare = round(statistics.mean(paired) / statistics.mean(bare), 2)
        print(
            f"  bare `docker run -d` {mean(bare)} s; docker runtime sequential / bare = {docker_over_bare} (goal <=1.1)"
        )
    proc, dock = results.get("process", {}), results.get("docker", {})
    figures = {
        "seq_init_s": mean(proc.get("seq")),
        "parallel_init_s": mean(proc.get("parallel")),
        "seq_init_docker_s": mean(dock.get("seq")),
        "parallel_init_docker_s": mean(dock.get("parallel")),
        "bare_docker_run_s": mean(bare),
        "docker_over_bare": docker_over_bare,
        "max_concurrent_skills_process": proc.get("max"),
        "max_concurrent_skills_docker": dock.get("max"),
        "mb_per_extra_skill": round(proc["mb_per_skill"], 3) if proc.get("mb_per_skill") is not None else None,
        "mb_per_extra_skill_docker": round(dock["mb_per_skill"], 3) if dock.get("mb_per_skill") is not None else None,
    }
    report(figures)
    return 0


if __name__ == "__main__":
    sys.exit(main())
