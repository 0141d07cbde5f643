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
RAM and radio times their hourly consumption, constants in _usecases_run.py). Performance per Skill:

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

With ``--cloud-mb 35`` people detection also runs with the thesis's 30-40 MB clouds (§5.3.1), its
topics relayed by the real Skill Router (TCPROS, on the robot, inside the robot's cgroup) as in
the thesis: each combination measures the seconds from the camera's stamp to the detections, the
peak RSS of the router and of each node, and what the router dropped. The figures are printed
beside Table 5.2's, and added to the last line as ``people_detection_<MB>mb_*`` keys.

    .venv/bin/python benchmarks/usecases.py --quick --cloud-mb 35 --skills=   # only the big clouds, 2 combos

The last line is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

import _netshape
from _common import ROOT, log
from _harness import arguments, report
from _usecases_run import (
    BIG_CLOUD_RATE,
    ENERGY_W,
    ROBOT_RAM_MIB,
    SKILLS,
    USECASE,
    Measurement,
    RobotCgroup,
    Run,
    big_cloud_run,
    measure,
    placements,
    robot_and_cloud,
)
from _usecases_tables import best_of, big_figures, big_table, change_pct, rounded, table

from bridgeos_agent.ros2graph import rclpy_missing
from bridgeos_agent.skillconfig import load_sample_skill_config


def main(argv: list[str] | None = None) -> int:
    parser = arguments(__doc__, "all-robot and all-cloud only, short windows")
    parser.add_argument("--preset", default="wifi", choices=sorted(_netshape.PRESETS), help="the robot-cloud link")
    parser.add_argument("--robot-cpu", type=float, default=0.5, help="cores the robot's components get (0.1-2)")
    parser.add_argument("--window", type=float, default=None, help="seconds measured per combination")
    parser.add_argument("--warmup", type=float, default=None, help="seconds after the first result before measuring")
    parser.add_argument("--skills", default=",".join(SKILLS), help="comma-separated Skills to run")
    parser.add_argument(
        "--cloud-mb", type=float, default=None, help="also run people detection with clouds this big (thesis: 30-40)"
    )
    parser.add_argument(
        "--cloud-rate", type=float, default=BIG_CLOUD_RATE, help=f"clouds a second with --cloud-mb ({BIG_CLOUD_RATE:g})"
    )
    parser.add_argument(
        "--cloud-frames",
        type=int,
        default=None,
        help="detections each --cloud-mb window waits for (default 6, quick 1)",
    )
    parser.add_argument("--ros", type=int, default=1, choices=(1, 2), help="run the Skills' ROS 1 or ROS 2 nodes")
    parser.add_argument(
        "--ros-domain", type=int, default=int(os.environ.get("ROS_DOMAIN_ID") or 0), help="ROS_DOMAIN_ID (--ros 2)"
    )
    parser.add_argument("--out", type=Path, default=ROOT / ".data" / "bench" / "usecases.md", help="matrix table")
    args = parser.parse_args(argv)
    skills = [s for s in args.skills.split(",") if s]
    unknown = set(skills) - set(SKILLS)
    if args.cloud_mb is not None and not 1 <= args.cloud_mb <= 100:
        parser.error("--cloud-mb is between 1 and 100 MB")
    if not 0.01 <= args.cloud_rate <= 10 or (args.cloud_frames is not None and not 1 <= args.cloud_frames <= 100):
        parser.error("--cloud-rate is between 0.01 and 10 clouds a second, --cloud-frames between 1 and 100")
    if unknown or not (skills or args.cloud_mb):
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
                run = Run(skill, config, where, link, cgroup, Path(tmp), ros=args.ros, domain_id=args.ros_domain)
                log(f"{skill} {index}/{len(combos)}: " + ", ".join(f"{c}@{w}" for c, w in where.items()))
                try:
                    row = measure(run, warmup, window, link_mbit, args.robot_cpu, patience=60)
                finally:
                    run.stop()
                results[skill].append(row)
            tables.append(table(skill, results[skill]))
            log("\n" + tables[-1])
        if args.cloud_mb is not None:
            # --quick: one detection past the first per combination, no warm-up (a 35 MB cloud takes 7 s on wifi).
            frames = args.cloud_frames or (1 if args.quick else 6)
            big_warmup = 0.0 if args.quick else warmup
            big = run_big_clouds(args, link, cgroup, Path(tmp), link_mbit, big_warmup, window, frames)
            tables.append(big_table(big, args.cloud_mb, args.cloud_rate))
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
        figures[f"{skill}_performance_pct"] = rounded(change_pct(best.performance, base.performance, higher))
        for key, attr in (("cpu", "cpu_pct"), ("ram", "ram_mib"), ("network", "network_kbps"), ("power", "power_w")):
            figures[f"{skill}_{key}_pct"] = rounded(change_pct(getattr(best, attr), getattr(base, attr)))
    figures["delivery_ratio"] = round(1 - statistics.fmean(losses) / 100, 4) if losses else None
    figures["skill_init_s"] = round(statistics.median(inits), 2) if inits else None
    if args.cloud_mb is not None:
        figures.update(big_figures(big, args.cloud_mb))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n\n".join(tables) + "\n")
    log(f"matrix written to {args.out}")
    report(figures)
    return 0


def run_big_clouds(
    args: argparse.Namespace,
    link: _netshape.Link,
    cgroup: RobotCgroup,
    home: Path,
    link_mbit: float,
    warmup: float,
    window: float,
    frames: int,
) -> list[Measurement]:
    """Run people detection with thesis-sized clouds through the Skill Router, per combination."""
    spec = big_cloud_run(args.cloud_mb, args.cloud_rate)
    config = load_sample_skill_config(spec.sample)
    combos = placements(config)
    if args.quick:
        combos = [combos[0], combos[-1]]
    rows = []
    for index, where in enumerate(combos, 1):
        run = Run("people_detection", config, where, link, cgroup, home, spec)
        log(f"people detection, {args.cloud_mb:g} MB clouds {index}/{len(combos)}: " + _where(where))
        try:
            # The first cloud is rendered on the capped robot and may queue behind the link: patience.
            rows.append(measure(run, warmup, window, link_mbit, args.robot_cpu, patience=120, min_results=frames))
        finally:
            run.stop()
        row = rows[-1]
        log(
            f"  {row.results} detections, median {row.performance or float('nan'):.0f} ms, router dropped "
            f"{row.relay_dropped}, peak RSS MiB " + ", ".join(f"{k} {v:.0f}" for k, v in row.peak_rss_mib.items())
        )
    return rows


def _where(where: dict[str, str]) -> str:
    """Name a combination: each component at its location."""
    return ", ".join(f"{c}@{w}" for c, w in where.items())


if __name__ == "__main__":
    sys.exit(main())
