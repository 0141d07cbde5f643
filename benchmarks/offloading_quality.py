"""Offloading quality: the Skill Manager against every static placement and the hindsight oracle (issue 10).

A real cloud (daphne started here, PostgreSQL, Redis, a Celery worker starting cloud copies
with the process runtime), the real Robot Controller with the process runtime and the real
Skill Manager run a Skill of four movable components on a simulated robot
(``monitor.SimulatedRobot``) whose background CPU load and link bandwidth follow scripted
phases (idle or busy robot, good or poor link), with noise. The components burn the CPU they
declare, so the runtime's measurements are real. The Skill's custom policy costs each component as a delay:
on the robot its CPU over the robot's free CPU, in the cloud a round trip plus its data over the
link's bandwidth (``POLICY`` in _offloading_scenario.py). The robot is sampled and the manager
decides every quarter second (threshold 2 and hysteresis 3, in the policy's units, a few percent of
a cost; cooldown 4 s), and moves decided together go together.

Every placement the run went through is costed afterwards with the same PolicyEstimator and cost
functions, from the script's noiseless conditions and the components' declared usage, and
compared with: every static placement (2^4 of them) and the hindsight oracle, which runs the best
static placement of each phase from the phase's first instant. Printed: cost relative to the
oracle (goal <= 1.05), time to adapt after each change (goal <= 10 s; adapted = a placement
costing at most 5 % more than the phase's best), migrations, and flaps (a move reversed within 60 s
with no change of conditions in between).

After the changing phases the script holds one long stable phase (``--stable-s``): a moderate load
that leaves one component near its decision boundary, with three times the noise. Conditions do not
change in it, so every move there after its first SETTLE_S seconds (the adaptation goal) is noise:
``stable_moves_per_10min`` counts them (goal <= 1 per 10 minutes), and so does ``flaps_per_10min``, as
issue 22 asks (flapping counted over a long stable phase, not over phase changes; every move there
counts, reversed or not). ``flaps_changing_per_10min`` counts the moves reversed within 60 s in the
changing phases. ``cost_over_oracle`` covers the changing phases; ``adapt_s`` covers
every change, the one into the stable phase included.

The misdeclared scenario (issue 22) runs beside it, in the same run, on two more robots with the
same script and seed: the detector declares a tenth of the 0.2 cores it burns, and those robots'
runtimes enforce no cgroup limit (held to its declaration it would be throttled instead), and their
simulated CPU reading counts what it burns beyond its declaration while it runs on the robot (the
simulated load otherwise follows declarations, where a real robot's reading, and the costing, follow
what is burnt). One robot's
manager decides by the estimate alone (its network never reaches ``trained_after``), the other's
learns from outcomes (``decision``: the network learns what the component cost where it ran and
decides once it beats the estimate on held-out outcomes). Both are costed with what the components
really burn: ``estimate_only_over_oracle_misdeclared`` and ``cost_over_oracle_misdeclared`` (goal
<= 1.10), and ``learned_decisions_share``, the share of the learned robot's adaptive decisions its
networks took. ``--no-misdeclared`` runs the main robot alone.

    .venv/bin/python benchmarks/offloading_quality.py --quick     # 4 phases of 8 s, then 14 s stable
    .venv/bin/python benchmarks/offloading_quality.py             # 8 phases of 60 s, then 300 s stable
    .venv/bin/python benchmarks/offloading_quality.py --quick --ros 2   # the components as ROS 2 nodes

With ``--ros 2`` each component is a ROS 2 node (``"ros": 2``, rclpy from the agent's venv) burning
the same CPU in its timer and publishing its load on ``load``, in a graph of its own
(``--ros-domain``, discovery on loopback): the same decisions, on ROS 2 components.

The last line is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _cloudlinks
from _common import ROOT, log
from _harness import arguments, cloud, report
from _offloading_scenario import (
    CLOUD_RATE_HZ,
    COMPONENTS,
    CPU_CORES,
    DECISION_INTERVAL,
    ESTIMATE_ROBOT,
    FULL_SCRIPT,
    LAN_MBITS,
    LEARNED_ROBOT,
    MISDECLARED,
    MISDECLARED_SHARE,
    QUICK_SCRIPT,
    ROBOT_CONFIG,
    ROBOT_ID,
    SAMPLE_INTERVAL,
    SETTLE_S,
    SKILL_ID,
    STABLE,
    TIMELINE_STEP,
    Script,
    ScriptedRobot,
    size_clouds,
    skill_config,
)
from _offloading_scoring import Costing, Run, adaptation, flaps, integrate, over_oracle, reward_noise, stable_moves

from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.decisionmodel import _load_torch
from bridgeos_agent.ros2graph import rclpy_missing
from bridgeos_agent.runtime.cgroups import Cgroups
from bridgeos_agent.skillconfig import SkillConfig

# --------------------------------------------------------------------------- the run


async def run_scenario(
    ws_url: str,
    token: str,
    script: Script,
    data_dir: Path,
    config: SkillConfig,
    robot_id: str = ROBOT_ID,
    started: asyncio.Event | None = None,
) -> Run:
    """Run the controller and its manager through the script; record placements and moves (set ``started``)."""
    robot = ScriptedRobot(cpu=CPU_CORES, ram=4096, bandwidth=LAN_MBITS, seed=7, script=script)
    settings = AgentSettings(
        master=ws_url,
        robot=robot_id,
        token=token,
        data_dir=data_dir,
        simulate=True,
        simulated=robot,
        sample_interval=SAMPLE_INTERVAL,
        detect_ros_master=False,
        stop_components_on_exit=True,
        # The runtime holds a component to its declared CPU with cgroups: a misdeclared one would be
        # throttled to a tenth of its work rather than burn what it needs. Its robot enforces nothing,
        # as one whose agent cannot write cgroups (the others burn exactly what they declare anyway).
        runtime_options={"cgroups": Cgroups(robot_id, hierarchy=None)} if robot_id != ROBOT_ID else {},
    )
    controller = RobotController(settings, say=lambda line: log(f"agent {robot_id}: {line}"))
    task = asyncio.create_task(controller.run())
    run = Run()
    names = list(config.components)
    try:
        await asyncio.wait_for(controller.config_from_cloud.wait(), 60)
        record = await controller.start_skill(config)
        if record.status != "running":
            raise RuntimeError(f"the Skill did not start: {record.status}")
        hidden = {
            name: COMPONENTS[name]["cpu"] - component.resources.cpu
            for name, component in config.components.items()
            if COMPONENTS[name]["cpu"] > component.resources.cpu
        }
        if hidden:
            robot.undeclared = lambda: sum(c for n, c in hidden.items() if record.locations.get(n) == "robot")
        script.start = time.time()
        if started is not None:
            started.set()
        log(f"skill running; script of {len(script.phases)} phases x {script.phase_s:.0f} s starts")
        last = None
        phase_index = -1
        loop = asyncio.get_running_loop()
        next_at = loop.time()
        while (elapsed := time.time() - script.start) < script.duration:
            index = script.index(elapsed)
            if index != phase_index:
                phase_index = index
                log(f"{robot_id} t={elapsed:5.1f} s phase {index + 1}: {script.phases[index].name}")
            # A component between two places (or stopped) loads the robot no more: costed as in the cloud.
            placement = tuple(record.locations.get(name) or "cloud" for name in names)
            if last is not None:
                for name, before, after in zip(names, last, placement, strict=True):
                    if before != after:
                        run.moves.append((elapsed, name, before, after))
                        log(f"{robot_id} t={elapsed:5.1f} s {name}: {before} -> {after}")
            last = placement
            run.timeline.append((elapsed, placement))
            manager = record.supervisor.context.get("manager") if record.supervisor else None
            for name, decision in (manager.last if manager is not None else {}).items():
                run.rewards.setdefault(name, {})[decision.at] = (elapsed, decision.estimated_reward)
                run.decided_by[(name, decision.at)] = decision.decided_by
            next_at += TIMELINE_STEP
            await asyncio.sleep(max(0.0, next_at - loop.time()))
        manager = record.supervisor.context.get("manager") if record.supervisor else None
        if manager is not None:
            for decider in manager.deciders.values():
                run.trained += decider.model.trained
            run.decisions = sum(d.model.samples_seen for d in manager.deciders.values())
            run.trusted = sum(1 for d in manager.last.values() if d.trusted)
            run.robot_errors = {name: decider.errors("robot") for name, decider in manager.deciders.items()}
        await controller.stop_skill(SKILL_ID)
    finally:
        controller.stop()
        await asyncio.wait_for(task, 60)
    return run


# --------------------------------------------------------------------------- figures


async def run_all(
    ws_url: str,
    tokens: dict[str, str],
    script: Script,
    data_dir: Path,
    scenarios: dict[str, SkillConfig],
    beside: tuple[float, Callable[[], object]] | None = None,
) -> dict[str, Run]:
    """Run every scenario's robot at once, each through its own copy of the script.

    beside: (t, start) calls ``start`` once the main robot's script has run t seconds.
    """
    started = asyncio.Event()  # the main robot's script started

    async def start_beside(at: float, start: Callable[[], object]) -> None:
        await started.wait()
        await asyncio.sleep(at)
        start()

    aside = asyncio.create_task(start_beside(*beside)) if beside is not None else None
    try:
        runs = await asyncio.gather(
            *(
                run_scenario(
                    ws_url,
                    tokens[robot_id],
                    replace(script),
                    data_dir / f"agent-{robot_id}",
                    config,
                    robot_id,
                    started if robot_id == ROBOT_ID else None,
                )
                for robot_id, config in scenarios.items()
            )
        )
    finally:
        if aside is not None:
            aside.cancel()
    return dict(zip(scenarios, runs, strict=True))


def make_robots(args: argparse.Namespace) -> tuple[SkillConfig, dict[str, SkillConfig], dict[str, str]]:
    """Create each scenario's robot with its Skill; return the main Skill, every robot's, and their tokens."""
    from django.contrib.auth import get_user_model

    from robots.models import Robot
    from robots.services import create_robot, update_robot_config
    from skills.services import add_skill

    config = skill_config(args.noise_margin, args.ros, args.ros_domain)
    scenarios = {ROBOT_ID: config}
    if args.misdeclared:
        scenarios[ESTIMATE_ROBOT] = skill_config(
            args.noise_margin, args.ros, args.ros_domain, misdeclared=True, learn=False
        )
        scenarios[LEARNED_ROBOT] = skill_config(args.noise_margin, args.ros, args.ros_domain, misdeclared=True)
    owner, _ = get_user_model().objects.get_or_create(username="offload-bench")
    tokens = {}
    for robot_id, scenario in scenarios.items():
        Robot.objects.filter(id=robot_id).delete()
        robot, tokens[robot_id] = create_robot(robot_id, owner)
        update_robot_config(robot.id, ROBOT_CONFIG)
        add_skill(robot, scenario.model_dump(mode="json"))
    return config, scenarios, tokens


def main() -> None:
    parser = arguments(
        __doc__, "4 phases of 8 s, 14 s stable: under a minute", database="bridgeos_bench_offloading", redis=10
    )
    parser.add_argument("--phase-s", type=float, help="seconds per phase (default 60, --quick 8)")
    parser.add_argument(
        "--stable-s", type=float, help="seconds of the stable phase after the changes (default 300, --quick 14, 0 none)"
    )
    parser.add_argument(
        "--noise-margin", type=float, help="the manager's noise_margin (default: its own; 0 waits for no confirmation)"
    )
    parser.add_argument(
        "--cloud-mb", type=float, help="the sampler takes pointclouds this big (thesis: 30-40 MB) at 0.2 Hz"
    )
    parser.add_argument(
        "--no-misdeclared",
        dest="misdeclared",
        action="store_false",
        help="skip the misdeclared scenario's two robots (run beside the main one by default)",
    )
    parser.add_argument(
        "--ros",
        type=int,
        default=0,
        choices=(0, 2),
        help="2: the components are ROS 2 nodes (default: plain processes)",
    )
    parser.add_argument(
        "--ros-domain", type=int, default=int(os.environ.get("ROS_DOMAIN_ID") or 0), help="ROS_DOMAIN_ID (--ros 2)"
    )
    parser.add_argument("--no-cloud-links", action="store_true", help="skip the robot-link bytes run (_cloudlinks.py)")
    args = parser.parse_args()
    if args.cloud_mb is not None:
        if not 1 <= args.cloud_mb <= 100:
            parser.error("--cloud-mb is between 1 and 100 MB")
        size_clouds(args.cloud_mb)
        log(f"{args.cloud_mb:g} MB clouds at {CLOUD_RATE_HZ:g} Hz: the sampler declares {COMPONENTS['sampler']}")
    # --quick stays under a minute with its stable phase: shorter changing phases, a 14 s stable one.
    phase_s = args.phase_s or (8.0 if args.quick else 60.0)
    if phase_s < 2 * DECISION_INTERVAL:
        parser.error(f"--phase-s must be at least {2 * DECISION_INTERVAL} s")
    if args.ros == 2 and rclpy_missing():
        parser.error(f"--ros 2 needs rclpy: {rclpy_missing()}")
    if not 0 <= args.ros_domain <= 232:
        parser.error("--ros-domain is 0-232")
    stable_s = args.stable_s if args.stable_s is not None else (14.0 if args.quick else 300.0)
    if stable_s and stable_s <= SETTLE_S:
        parser.error(f"--stable-s must be 0 or more than {SETTLE_S} s (its first {SETTLE_S} s are adaptation)")
    changing = QUICK_SCRIPT if args.quick else FULL_SCRIPT
    script = Script([*changing, STABLE] if stable_s else changing, phase_s, stable_s=stable_s)
    load_before = os.getloadavg()
    log(f"machine load {load_before[0]:.2f} {load_before[1]:.2f} {load_before[2]:.2f} on {os.cpu_count()} cores")
    # Issue 22: bytes on the robot's link with every movable component in the cloud, after cloud-side
    # routing over before (a ROS pipeline of its own on a real link). --quick measures it beside the
    # scenario to stay under a minute, from the change to the poor link on (moves there go to the robot,
    # which loads no cloud start; it ends before the stable phase); the full run after it, so nothing
    # else shares the machine.
    links: list[Callable[[], float | None]] = []
    beside = None
    if args.quick and not args.no_cloud_links:
        beside = (2 * phase_s, lambda: links.append(_cloudlinks.figure_beside(quick=True)))
    # An agent imports torch once, at its first movable Skill; here that would eat the first phase
    # (8 s under load, the managers' decisions waiting for it), so it is imported before the script,
    # while the database is migrated (--quick stays under a minute).
    torch_loaded = threading.Thread(target=_load_torch, name="torch")
    torch_loaded.start()

    cloud_id = f"bench-offload-{os.getpid()}"
    env = {
        # The cloud side is real: a Celery worker starts each cloud copy with the process runtime.
        "BRIDGEOS_CLOUD_ID": cloud_id,
        "BRIDGEOS_CLOUD_RUNTIME": "process",
        "BRIDGEOS_CLOUD_ROS_MASTERS": "0",
        "CELERY_TASK_DEFAULT_QUEUE": f"{cloud_id}-q",
    }
    # Migrated in this process (one Django start less); daphne is killed after 3 s, not 15: closing its
    # last sockets politely can take that long.
    with cloud(
        args,
        "bridgeos-bench-offloading-",
        env=env,
        flush_redis=False,
        migrate_here=True,
        stop_timeout=3.0,
        remove_data=True,
    ) as bench:
        from django.core.management import call_command

        from monitoring.models import Event

        try:
            daphne = bench.start_daphne(wait=False)
            # One pool process a core, as scripts/run.sh runs the worker here: a cloud start is CPU work, and the
            # pool of six this had (two a robot, for their simultaneous starts at a phase change) shared the two
            # cores among a burst, so that every start of it waited for all of them (a phase-2 move 0.3 s later).
            celery = bench.start_celery(env["CELERY_TASK_DEFAULT_QUEUE"], concurrency=os.cpu_count() or 2, wait=False)
            config, scenarios, tokens = make_robots(args)  # while daphne and the worker start
            daphne.wait()
            celery.wait()
            torch_loaded.join()
            log(f"daphne pid {daphne.pid} on port {daphne.port}, Celery worker pid {celery.process.pid}")
            runs = asyncio.run(run_all(daphne.ws_url, tokens, script, bench.data_dir, scenarios, beside))
            run = runs[ROBOT_ID]
        finally:
            bench.stop()
            call_command("cloud_down", stdout=open(os.devnull, "w"))  # no cloud copy outlives the run
        log("costing every placement")
        logged = list(
            Event.objects.filter(robot_id=ROBOT_ID, kind="offloading_decision").values_list("data", flat=True)
        )

    costing = Costing(config)
    adaptive, adaptive_phases = integrate(run, script, costing)
    best = [min(costing.placements(), key=lambda p, ph=phase: costing.rate(p, ph)) for phase in script.phases]
    lengths = [end - start for start, end in map(script.bounds, range(len(script.phases)))]
    oracle_phases = [costing.rate(best[i], phase) * lengths[i] for i, phase in enumerate(script.phases)]
    # The cost figures cover the changing phases, as they did before the stable phase was added.
    changes = range(script.changing)
    adaptive = sum(adaptive_phases[i] for i in changes)
    oracle = sum(oracle_phases[i] for i in changes)
    statics = {
        placement: sum(costing.rate(placement, script.phases[i]) * script.phase_s for i in changes)
        for placement in costing.placements()
    }
    best_static = min(statics, key=statics.get)
    adapts = adaptation(run, script, costing, best)
    changes_end = script.bounds(script.changing - 1)[1]
    flapped = [(t, name) for t, name in flaps(run, script) if t < changes_end]
    minutes = changes_end / 60
    flaps_per_10min = len(flapped) * 10 / minutes
    noise_moves = stable_moves(run, script)
    stable_minutes = max(0.0, script.stable_s - SETTLE_S) / 60
    stable_per_10min = len(noise_moves) * 10 / stable_minutes if stable_minutes else None
    stable_ratio = adaptive_phases[-1] / oracle_phases[-1] if script.stable_s else None
    adapt_values = [a["adapt_s"] if a["adapt_s"] is not None else lengths[a["phase"] - 1] for a in adapts]
    load_after = os.getloadavg()

    names = list(config.components)

    def short(placement: tuple[str, ...]) -> str:
        return " ".join(f"{n[:3]}:{w[0].upper()}" for n, w in zip(names, placement, strict=True))

    print(f"{'phase':4} {'conditions':24} {'oracle placement':32} {'adaptive/oracle':>15} {'adapted':>8} {'exact':>7}")
    for i, phase in enumerate(script.phases):
        a = adapts[i]
        ratio = adaptive_phases[i] / oracle_phases[i]
        adapted = "never" if a["adapt_s"] is None else f"{a['adapt_s']:.1f} s"
        exact = "never" if a["exact_s"] is None else f"{a['exact_s']:.1f} s"
        print(f"{i + 1:<5} {phase.name:24} {short(best[i]):32} {ratio:15.3f} {adapted:>8} {exact:>7}")
    print()
    print(f"{'placement':40} {'cost':>10} {'over oracle':>12}")
    print(f"{'hindsight oracle (best static per phase)':40} {oracle:10.0f} {1:12.3f}")
    print(f"{'adaptive (Skill Manager)':40} {adaptive:10.0f} {adaptive / oracle:12.3f}   goal <= 1.05")
    print(
        f"{'best static: ' + short(best_static):40} {statics[best_static]:10.0f} {statics[best_static] / oracle:12.3f}"
    )
    for label, placement in (("all on the robot", ("robot",) * 4), ("all in the cloud", ("cloud",) * 4)):
        print(f"{label:40} {statics[placement]:10.0f} {statics[placement] / oracle:12.3f}")
    worst = max(statics, key=statics.get)
    print(f"{'worst static: ' + short(worst):40} {statics[worst]:10.0f} {statics[worst] / oracle:12.3f}")
    print()
    moved = sum(1 for d in logged if d.get("outcome") == "moved")
    failed = sum(1 for d in logged if d.get("outcome") == "failed")
    mean_adapt = sum(adapt_values) / len(adapt_values)
    print(f"time to adapt: max {max(adapt_values):.1f} s, mean {mean_adapt:.1f} s   goal <= 10 s")
    print(f"migrations: {len(run.moves)} seen ({moved} logged as moved, {failed} failed in the cloud's event log)")
    print(f"flaps: {len(flapped)} in {minutes:.1f} min of changes = {flaps_per_10min:.2f} per 10 min")
    if stable_per_10min is not None:
        print(
            f"stable phase: {len(noise_moves)} moves in {stable_minutes:.1f} min after its first {SETTLE_S:.0f} s"
            f" = {stable_per_10min:.2f} per 10 min   goal <= 1"
        )
        spread = ", ".join(f"{name} {sd:.2f}" for name, sd in reward_noise(run, script).items())
        print(f"stable phase: estimated reward standard deviation (cost units): {spread}")
    print(f"decision networks trained: {run.trained}/{len(names)}; last decisions by a trusted network: {run.trusted}")
    print(f"main run: {100 * run.learned_share:.0f} % of the adaptive decisions taken by the network")
    misdeclared: dict[str, float | None] = {"learned": None, "estimate": None}
    learned_share = run.learned_share
    if args.misdeclared:
        # Costed with what the components really burn: the truthful config's declarations.
        misdeclared = {
            "estimate": over_oracle(runs[ESTIMATE_ROBOT], script, costing),
            "learned": over_oracle(runs[LEARNED_ROBOT], script, costing),
        }
        learned_share = runs[LEARNED_ROBOT].learned_share
        share = MISDECLARED_SHARE
        print(f"misdeclared ({MISDECLARED} declares {share:g} of the CPU it burns), cost over the oracle:")
        for label, key in (("estimate only", ESTIMATE_ROBOT), ("learning from outcomes", LEARNED_ROBOT)):
            other = runs[key]
            ratio = misdeclared["estimate" if key == ESTIMATE_ROBOT else "learned"]
            print(
                f"  {label:24} {ratio:.3f}  migrations {len(other.moves)}, "
                f"{100 * other.learned_share:.0f} % of the decisions by the network"
            )
        network, estimate = runs[LEARNED_ROBOT].robot_errors.get(MISDECLARED, (None, None))
        if network is not None and estimate is not None:
            print(f"  {MISDECLARED}'s held-out error on the robot: network {network:.3g}, estimate {estimate:.3g}")
    print(f"machine load (1 min) {load_before[0]:.2f} before, {load_after[0]:.2f} after, on {os.cpu_count()} cores")
    if links:
        link_ratio = links[0]()
    else:
        link_ratio = None if args.no_cloud_links else _cloudlinks.figure(args.quick)
    report(
        {
            "cost_over_oracle": round(adaptive / oracle, 4),
            "cost_over_oracle_misdeclared": _round(misdeclared["learned"]),
            "estimate_only_over_oracle_misdeclared": _round(misdeclared["estimate"]),
            "learned_decisions_share": round(learned_share, 4),
            "adapt_s": round(max(adapt_values), 2),
            # Issue 22: flapping over the long stable phase (every move there), else over the changes.
            "flaps_per_10min": round(stable_per_10min if stable_per_10min is not None else flaps_per_10min, 3),
            "flaps_changing_per_10min": round(flaps_per_10min, 3),
            "migrations": len(run.moves),
            "adapt_mean_s": round(mean_adapt, 2),
            "best_static_over_oracle": round(statics[best_static] / oracle, 4),
            "all_robot_over_oracle": round(statics[("robot",) * 4] / oracle, 4),
            "all_cloud_over_oracle": round(statics[("cloud",) * 4] / oracle, 4),
            "moves_logged": moved,
            "moves_failed": failed,
            "stable_moves_per_10min": None if stable_per_10min is None else round(stable_per_10min, 3),
            "stable_moves": len(noise_moves),
            "stable_over_oracle": None if stable_ratio is None else round(stable_ratio, 4),
            "stable_s": stable_s,
            "phases": len(script.phases),
            "phase_s": phase_s,
            "load_1min": round(load_after[0], 2),
            "robot_link_bytes_all_cloud_over_before": link_ratio,
            "ros": args.ros,
        }
    )


def _round(value: float | None) -> float | None:
    return None if value is None else round(value, 4)


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
