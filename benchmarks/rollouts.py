"""Fleet rollouts: a good release to 1,000 simulated robots, a bad one rolled back, an offline robot converging.

The cloud is real (daphne, PostgreSQL, Redis); the robots are simulated, many per process over the
real wire protocol (benchmarks/_simfleet.py: each answers Skill orders as a Robot Controller does),
and the rollout executor's steps are the Celery beat task's own function, called every
BRIDGEOS_ROLLOUT_TICK_S here, in a process of its own as a Celery worker's. Phases, on one fleet
running release 1 of a Skill:

1. release 2 to every robot: 10 % first, batches doubling, no pause, a 2 s soak; while it rolls,
   a reader asks the Robot API for robots and for the rollout (p99 of those reads);
2. release 3, whose first component crashes half a second after it starts, with a 10 % canary
   and a 5 % failure threshold: how many robots it touched, and from the first failed gate until
   every touched robot reported release 2 running again;
3. one robot offline while release 4 is rolled out to it: from its reconnection (a controller
   restarting) until it reports release 4 running.

    .venv/bin/python benchmarks/rollouts.py --quick      # 200 robots
    .venv/bin/python benchmarks/rollouts.py              # 1,000 robots
"""

from __future__ import annotations

import asyncio
import multiprocessing as mp
import os
import sys
import threading
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ROOT, log, percentile, setup_django
from _harness import Clients, arguments, cloud, create_fleet, forget_fleet, machine_load, report, shares
from _simfleet import SimRobot, fleet_worker

PREFIX = "rollout-bench-"
OWNER = "rollout-bench-owner"
SKILL = "detector"
TICK_S = 0.25


def detector(version: int, *, crash: bool = False) -> dict[str, Any]:
    """Release ``version`` of a two-component Skill (process components: nothing to pull)."""
    from bridgeos_agent.skillconfig import parse_skill_config

    spec = {"command": ["sleep", "600"]}
    components = {
        name: {"name": name, "location": "robot", "ros": False, "resources": {"cpu": 0.1, "ram": 16}, "robot": spec}
        for name in ("camera", "detect")
    }
    name = f"Detector {version}" + (" crash" if crash else "")
    return parse_skill_config({"skill": name, "skill_id": SKILL, "components": components}).model_dump(mode="json")


def prepare(robots: int) -> dict[str, Any]:
    """A fleet running release 1 (rows as the robots would have reported them) and one robot kept apart."""
    from django.contrib.auth import get_user_model

    from robots.models import Robot
    from robots.services import issue_api_token
    from rollouts.models import Release, Rollout
    from skills.models import Component, Skill
    from teams.services import personal_organization

    Rollout.objects.filter(organization__slug=OWNER).delete()
    Release.objects.filter(organization__slug=OWNER).delete()
    forget_fleet(PREFIX, events=True)
    owner, _ = get_user_model().objects.get_or_create(username=OWNER)
    first = detector(1)
    tokens = create_fleet(owner, robots + 1, PREFIX, digits=5, skills=[first], batch_size=1000)
    fleet, apart = tokens[:-1], tokens[-1]
    Robot.objects.filter(id__startswith=PREFIX).update(labels={"bench": "fleet"})
    Robot.objects.filter(id=apart[0]).update(labels={"bench": "apart"})
    Skill.objects.filter(robot__id__startswith=PREFIX).update(status="running")
    Component.objects.filter(skill__robot__id__startswith=PREFIX).update(status="running", active_location="robot")
    return {
        "owner": owner,
        "organization": personal_organization(owner),
        "fleet": fleet,
        "apart": apart,
        "api_token": issue_api_token(owner)[0],
    }


class Executor:
    """The rollout executor's beat in a process of its own, as a Celery worker runs it: every TICK_S, a step."""

    def __init__(self, env: dict[str, str]) -> None:
        # Spawned, not forked: a forked child would share the parent's pooled database connections.
        context = mp.get_context("spawn")
        self.stop = context.Event()
        self._ticks = context.Queue()
        self.ticks: list[float] = []
        self.process = context.Process(target=beat, args=(env, self.stop, self._ticks), daemon=True)
        self.process.start()

    def join(self, timeout: float) -> None:
        """Stop the beat and collect how long its ticks took."""
        self.stop.set()
        self.ticks = self._ticks.get(timeout=timeout)
        self.process.join(timeout)


def beat(env: dict[str, str], stop: Any, ticks_out: Any) -> None:
    """Call the executor's tick every TICK_S until told to stop; hand back each tick's duration."""
    setup_django(env)
    from django.db import connection

    from rollouts import executor

    ticks: list[float] = []
    while not stop.wait(TICK_S):
        started = time.monotonic()
        executor.tick()
        ticks.append(time.monotonic() - started)
    connection.close()
    ticks_out.put(ticks)


class Reader:
    """Robot API reads while a rollout runs: one robot, the fleet's first page, the rollout."""

    def __init__(self, base: str, token: str, robot_ids: list[str]) -> None:
        self.base, self.token, self.robot_ids = base, token, robot_ids
        self.rollout_id: int | None = None
        self.latencies: list[float] = []
        self.failures = 0
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        import httpx

        with httpx.Client(base_url=self.base, headers={"Authorization": f"Token {self.token}"}, timeout=30) as http:
            n = 0
            while not self.stop.is_set():
                n += 1
                if n % 3 == 0 and self.rollout_id is not None:
                    path = f"/api/rollouts/{self.rollout_id}"
                elif n % 3 == 1:
                    path = f"/api/robot/{self.robot_ids[n % len(self.robot_ids)]}"
                else:
                    path = "/api/robot?limit=50"
                started = time.monotonic()
                ok = http.get(path).status_code == 200
                self.latencies.append((time.monotonic() - started) * 1000)
                self.failures += not ok
                time.sleep(0.1)


def wait_state(rollout_id: int, states: set[str], timeout: float) -> Any:
    from rollouts.models import Rollout

    deadline = time.monotonic() + timeout
    while True:
        rollout = Rollout.objects.get(pk=rollout_id)
        if rollout.state in states:
            return rollout
        if time.monotonic() > deadline:
            raise TimeoutError(f"rollout {rollout_id} is {rollout.state} ({rollout.reason}) after {timeout} s")
        time.sleep(0.05)


def good_release(world: dict[str, Any], base: str, robots: int) -> dict[str, Any]:
    from rollouts.rolling import create_rollout
    from rollouts.services import create_release

    made = create_release(world["organization"], detector(2), user=world["owner"])
    reader = Reader(base, world["api_token"], [robot_id for robot_id, _ in world["fleet"]])
    time.sleep(1.0)  # the reader's figures include the fleet at rest, then rolling
    started = time.monotonic()
    rollout = create_rollout(
        made, "bench=fleet", strategy={"first": "10%", "factor": 2, "pause_s": 0, "soak_s": 2}, user=world["owner"]
    )
    reader.rollout_id = rollout.id
    done = wait_state(rollout.id, {"succeeded", "rolled_back", "paused"}, timeout=600)
    took = time.monotonic() - started
    reader.stop.set()
    reader.thread.join(30)
    if done.state != "succeeded":
        raise RuntimeError(f"the good release ended {done.state}: {done.reason}")
    log(f"release 2 on {robots} robots in {took:.1f} s ({len(done.batch_sizes)} batches {done.batch_sizes})")
    p99 = percentile(reader.latencies, 0.99)
    log(f"{len(reader.latencies)} Robot API reads meanwhile, p99 {p99:.1f} ms, {reader.failures} failed")
    return {"rollout_1000_s": round(took, 2), "api_p99_ms_during_rollout": round(p99 or 0, 1)}


def bad_release(world: dict[str, Any]) -> dict[str, Any]:
    from monitoring.models import Event
    from rollouts.models import RolloutRobot
    from rollouts.rolling import create_rollout
    from rollouts.services import create_release

    made = create_release(world["organization"], detector(3, crash=True), user=world["owner"])
    strategy = {"first": "10%", "failure_threshold_pct": 5, "soak_s": 2}
    rollout = create_rollout(made, "bench=fleet", strategy=strategy, user=world["owner"])
    done = wait_state(rollout.id, {"succeeded", "rolled_back", "paused"}, timeout=300)
    if done.state != "rolled_back":
        raise RuntimeError(f"the bad release ended {done.state}: {done.reason}")
    members = RolloutRobot.objects.filter(rollout=rollout)
    touched = members.filter(touched=True).count()
    # The executor logs each failed gate when it happens; each robot's finished_at is when it ran release 2 again.
    failed = Event.objects.filter(kind="rollout", level="error", data__rollout=rollout.id, robot_id__isnull=False)
    failed_at = failed.order_by("ts").values_list("ts", flat=True).first()
    back_at = max(m.finished_at for m in members.filter(touched=True))
    rollback_s = (back_at - failed_at).total_seconds()
    gate = done.reason
    log(f"release 3: canary {done.batch_sizes[0]}, touched {touched}, rolled back in {rollback_s:.2f} s ({gate})")
    return {
        "bad_release_robots_touched": touched,
        "bad_release_canary": done.batch_sizes[0],
        "rollback_s": round(rollback_s, 2),
    }


def offline_converge(world: dict[str, Any], url: str) -> dict[str, Any]:
    from rollouts.rolling import create_rollout
    from rollouts.services import create_release
    from skills.models import Skill

    robot_id, token = world["apart"]
    made = create_release(world["organization"], detector(4), user=world["owner"])
    rollout = create_rollout(made, "bench=apart", strategy={"first": 1, "soak_s": 1}, user=world["owner"])
    deadline = time.monotonic() + 30
    while rollout.robots.get().status != "offline":
        if time.monotonic() > deadline:
            raise TimeoutError("the apart robot was never marked offline")
        time.sleep(0.05)

    async def reconnect() -> float:
        stop = asyncio.Event()
        sim = SimRobot(url, robot_id, token, {SKILL: detector(1)})
        task = asyncio.ensure_future(sim.run(stop, restarted=True))
        started = time.monotonic()
        while True:
            skill = await asyncio.to_thread(lambda: Skill.objects.get(robot_id=robot_id, skill_id=SKILL))
            if sim.skills[SKILL]["skill"] == "Detector 4" and skill.status == "running":
                took = time.monotonic() - started
                break
            if time.monotonic() - started > 30:
                raise TimeoutError("the reconnected robot never ran release 4")
            await asyncio.sleep(0.02)
        await asyncio.to_thread(wait_state, rollout.id, {"succeeded"}, 30)
        stop.set()
        await task
        return took

    took = asyncio.run(reconnect())
    log(f"the offline robot ran release 4 {took:.2f} s after reconnecting")
    return {"offline_converge_s": round(took, 2)}


def main() -> None:
    parser = arguments(__doc__, "200 robots: under a minute", database="bridgeos_bench_rollouts", redis=8)
    parser.add_argument("--robots", type=int, default=1000)
    parser.add_argument("--procs", type=int, default=2, help="processes simulating the fleet")
    args = parser.parse_args()
    if args.quick:
        args.robots = min(args.robots, 200)
    log(machine_load())
    with cloud(args, "bridgeos-rollouts-", env={"BRIDGEOS_ROLLOUT_TICK_S": str(TICK_S)}) as bench:
        world = prepare(args.robots)
        log(f"created {args.robots} robots running release 1")
        daphne = bench.start_daphne()
        url = daphne.ws_url + "/ws/robot/"
        connected = mp.get_context("fork").Value("i", 0)
        clients = Clients(fleet_worker, shares(world["fleet"], args.procs), url, detector(1), connected)
        deadline = time.monotonic() + 60
        while connected.value < args.robots:
            if time.monotonic() > deadline:
                raise TimeoutError(f"only {connected.value} of {args.robots} simulated robots connected")
            time.sleep(0.1)
        log(f"{args.robots} simulated robots connected")
        executor = Executor(bench.env)
        try:
            figures: dict[str, Any] = {"robots": args.robots}
            cpu = daphne.cpu_seconds()
            figures |= good_release(world, f"http://127.0.0.1:{daphne.port}", args.robots)
            log(f"daphne used {daphne.cpu_seconds() - cpu:.1f} s of CPU during release 2")
            figures |= bad_release(world)
            figures |= offline_converge(world, url)
        finally:
            executor.join(30)
            log(
                f"executor: {len(executor.ticks)} ticks, longest {max(executor.ticks, default=0):.2f} s, "
                f"p50 {percentile(executor.ticks, 0.5) or 0:.3f} s"
            )
            clients.stop_event.set()
            clients.reports(60)
    report(figures)


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
