"""The Skill Router for ROS 2 (issue 18): routed vs direct rclpy, a switch under 1 kHz, mapping, memory.

Runs real rclpy talkers and listeners (tests/agent/ros2nodes.py, subprocesses) on a
loopback-only graph (ROS_DOMAIN_ID from the env, 44 by default) and the agent's SkillRouter
in this process:

- throughput: P talker/listener pairs at R Hz (0 = flat out), first direct rclpy to rclpy on
  the canonical names, then the same with the talkers in a component's robot namespace and
  the router relaying, in the same run: messages/s, routed/direct, delivery ratio (reliable
  QoS), added latency p50 (goals >= 0.6 of direct flat out, 1.0 delivery at nominal rates);
- switch: a 1 kHz talker on the robot and one in the cloud namespace, the router switched
  from one to the other while a canonical listener counts every message: lost and duplicated
  sequence numbers on either side of the cut (goal 0 and 0, as benchmarks/router.py's test);
- mapping: a router with 2,000 ROS 2 topics (200 with --quick) opens each topic's DDS endpoints
  as for components placed on the robot (the publisher instance's source, the canonical name,
  the subscriber instance's sink): ms per topic for the last tenth, with the rest mapped
  (goal <= 10), the mean, then ms per topic to open the cloud instances (a move), and the
  resident memory each topic adds (DDS endpoints are C++, so RSS, not tracemalloc).

    .venv/bin/python benchmarks/router_ros2.py --quick
    .venv/bin/python benchmarks/router_ros2.py [--ros1]   # --ros1 also runs benchmarks/router.py --quick

The last line is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ROOT, log, percentile
from _harness import arguments, report

os.environ.setdefault("ROS_DOMAIN_ID", "44")
os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
os.environ.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")

from bridgeos_agent.ros2graph import Ros2Graph, namespace_arguments, rclpy_missing
from bridgeos_agent.rosnames import instance_name
from bridgeos_agent.router import RouterSettings, SkillRouter
from bridgeos_agent.skillconfig import parse_skill_config

NODES = str(ROOT / "tests" / "agent" / "ros2nodes.py")
SKILL = "bench2"
PUB_NS = f"/bridgeos/{SKILL}/pub/robot"
# benchmarks/router.py on this machine (README, "Skill Router"), and the thesis (§5.4.1).
ROS1 = {
    "topic_map_ms": 1.6,
    "kb_per_topic": 1.8,
    "routed_over_direct": 0.65,
    "delivery_ratio": 1.0,
    "added_latency_p50_ms": 0.2,
}
THESIS = {"topic_map_ms": "443 +- 20", "kb_per_topic": "10", "delivery_ratio": "0.9842"}


def graph() -> Ros2Graph:
    return Ros2Graph(domain_id=int(os.environ["ROS_DOMAIN_ID"]), discovery_range="LOCALHOST")


async def until(check, seconds: float) -> bool:
    """Poll ``check`` until it holds or ``seconds`` pass; tell which."""
    deadline = time.monotonic() + seconds
    while True:
        if check():
            return True
        if time.monotonic() > deadline:
            return False
        await asyncio.sleep(0.05)


class Procs:
    """Run ros2nodes.py roles, each printing to a file of its own."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.running: dict[str, subprocess.Popen[bytes]] = {}

    def run(self, key: str, role: str, *args: str, namespace: str | None = None) -> None:
        env = {**os.environ, **graph().env(), "PYTHONUNBUFFERED": "1"}
        extra = namespace_arguments(namespace) if namespace else []
        out = (self.directory / f"{key}.out").open("wb")
        self.running[key] = subprocess.Popen(
            [sys.executable, NODES, role, *args, *extra], env=env, stdout=out, stderr=subprocess.DEVNULL
        )

    def lines(self, key: str) -> list[str]:
        path = self.directory / f"{key}.out"
        return path.read_text(errors="replace").splitlines() if path.exists() else []

    def heard(self, key: str) -> list[tuple[str, int, float]]:
        found = []
        for line in self.lines(key):
            parts = line.split()
            if len(parts) == 3 and parts[1].isdigit():
                found.append((parts[0], int(parts[1]), float(parts[2])))
        return found

    def sent(self, key: str) -> int | None:
        return next((int(line.split()[1]) for line in self.lines(key) if line.startswith("sent ")), None)

    def stop_all(self) -> None:
        for process in self.running.values():
            process.kill()
        for process in self.running.values():
            process.wait(10)
        self.running.clear()


def skill_config(topics: int, subscriber: bool = True):
    spec = {"command": ["true"]}
    components = {
        name: {"name": name.title(), "location": "either", "ros": 2, "robot": spec, "cloud": spec}
        for name in ("pub", "sub")
    }
    routes = [
        {
            "name": f"/bench{n}/data",
            "type": "std_msgs/msg/String",
            "publisher": "pub",
            "subscribers": ["sub"] if subscriber else [],
        }
        for n in range(topics)
    ]
    return parse_skill_config(
        {"skill": "Bench2", "skill_id": SKILL, "components": components, "router": {"topics": routes}}
    )


async def new_router(config) -> SkillRouter:
    router = SkillRouter(config, ros_master=None, settings=RouterSettings(http_host="127.0.0.1"))
    await router.set_ros2_graphs(graph())
    router.set_active("pub", "robot")
    router.set_active("sub", "robot")
    await router.start()
    return router


async def pairs_run(directory: Path, pairs: int, rate: float, seconds: float, routed: bool) -> dict:
    """Run ``pairs`` talker/listener pairs for ``seconds``; count what the listeners heard."""
    procs = Procs(directory)
    router = await new_router(skill_config(pairs, subscriber=False)) if routed else None
    try:
        for n in range(pairs):
            procs.run(f"l{n}", "listener", "--topic", f"/bench{n}/data")
        await until(lambda: all(procs.lines(f"l{n}")[:1] == ["ready"] for n in range(pairs)), 30)
        args = ["--rate", str(rate), "--duration", str(seconds), "--wait", "--settle", "1", "--linger", "3"]
        for n in range(pairs):
            if routed:
                procs.run(f"t{n}", "talker", "--topic", f"bench{n}/data", *args, namespace=PUB_NS)
            else:
                procs.run(f"t{n}", "talker", "--topic", f"/bench{n}/data", *args)
        await until(lambda: all(procs.sent(f"t{n}") is not None for n in range(pairs)), seconds + 40)
        await asyncio.sleep(1.5)  # the last messages in flight
        sent = sum(procs.sent(f"t{n}") or 0 for n in range(pairs))
        heard = [h for n in range(pairs) for h in procs.heard(f"l{n}")]
        latencies = [h[2] for h in heard]
        return {
            "pairs": pairs,
            "rate": rate,
            "sent": sent,
            "heard": len(heard),
            "msgs_per_s": len(heard) / seconds,
            "delivery": len(heard) / sent if sent else 0.0,
            "p50_ms": percentile(latencies, 50) or 0.0,
        }
    finally:
        procs.stop_all()
        if router is not None:
            await router.close()


async def switch_run(directory: Path, seconds: float) -> dict:
    """Switch a 1 kHz talker robot -> cloud under a canonical listener; count lost and duplicated."""
    procs = Procs(directory)
    router = await new_router(skill_config(1, subscriber=False))
    try:
        procs.run("listener", "listener", "--topic", "/bench0/data")
        # Open the topic at once (as ROS 1's router advertises it) and let the listener match first,
        # so every message from the first on can be counted, as benchmarks/router.py's test does.
        from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

        topic = router._topics["/bench0/data"]
        router._r2_open(topic, ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE)  # type: ignore[arg-type]
        await until(lambda: topic.canonical_pub.get_subscription_count() > 0, 30)  # type: ignore[union-attr]
        procs.run(
            "robot", "talker", "--topic", "bench0/data", "--tag", "robot", "--rate", "1000", "--wait", namespace=PUB_NS
        )
        procs.run(
            "cloud",
            "talker",
            "--topic",
            "bench0/data",
            "--tag",
            "cloud",
            "--rate",
            "1000",
            namespace=f"/bridgeos/{SKILL}/pub/cloud",
        )
        await until(lambda: len(procs.heard("listener")) >= 300, 30)
        if not await router.wait_ready("pub", "cloud", 30):
            raise SystemExit("the cloud talker never matched")
        await asyncio.sleep(seconds / 2)
        await router.switch("pub", "cloud")
        await asyncio.sleep(seconds / 2)
        heard = procs.heard("listener")
    finally:
        procs.stop_all()
        await router.close()
    tags = [tag for tag, _, _ in heard]
    cut = tags.index("cloud") if "cloud" in tags else len(tags)
    lost = duplicated = 0
    interleaved = set(tags[cut:]) - {"cloud"}
    for part, first in ((heard[:cut], 1), (heard[cut:], None)):
        seqs = [seq for _, seq, _ in part]
        if not seqs:
            continue
        start = first if first is not None else seqs[0]
        lost += len(set(range(start, max(seqs) + 1)) - set(seqs))
        duplicated += len(seqs) - len(set(seqs))
    return {"heard": len(heard), "lost": lost, "duplicated": duplicated + len(interleaved), "cut": cut}


def rss_kb() -> int:
    with open("/proc/self/statm") as statm:
        return int(statm.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024


async def mapping_run(topics: int) -> dict:
    """Open the DDS endpoints of ``topics`` routed topics; time and resident memory per topic.

    Each topic gets what the router opens once its publisher shows up with both components
    placed on the robot: the publisher instance's source, the canonical publication and the
    subscriber instance's sink. ``last_ms`` is the time per topic of the last tenth, with the
    rest already mapped; then the same topics' cloud instances are opened (a move's readiness).
    """
    from rclpy.qos import DurabilityPolicy, ReliabilityPolicy

    router = await new_router(skill_config(topics))
    try:
        router._r2_task.cancel()  # no publishers will come: open the endpoints here, timed
        ros2 = list(router._topics.values())
        tenth = max(1, topics // 10)
        before = rss_kb()
        started = time.perf_counter()
        for topic in ros2[:-tenth]:
            router._r2_open(topic, ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE)  # type: ignore[arg-type]
        last_started = time.perf_counter()
        for topic in ros2[-tenth:]:
            router._r2_open(topic, ReliabilityPolicy.RELIABLE, DurabilityPolicy.VOLATILE)  # type: ignore[arg-type]
        done = time.perf_counter()
        after = rss_kb()
        moved = time.perf_counter()
        router._r2_want("sub", "cloud")  # both cloud instances are placed: the sinks open here,
        for topic in ros2:  # and each cloud source as its publisher shows up
            name = instance_name(topic.route.name, SKILL, "pub", "cloud")
            router._r2_subscribe(topic, name, topic.sources[name], topic.qos.reliability, topic.qos.durability)
        moved_done = time.perf_counter()
        return {
            "topics": topics,
            "ms_per_topic": (done - started) * 1000 / topics,
            "last_ms": (done - last_started) * 1000 / tenth,
            "move_ms": (moved_done - moved) * 1000 / topics,
            "kb_per_topic": (after - before) / topics,
        }
    finally:
        await router.close()


async def main(args: argparse.Namespace) -> dict:
    missing = rclpy_missing()
    if missing:
        raise SystemExit(missing)
    with tempfile.TemporaryDirectory(prefix="router-ros2-") as tmp:
        directory = Path(tmp)
        if args.quick:
            matrix, seconds, topics = [(1, 0), (10, 100)], 1.5, 200
        else:
            matrix = [(1, 100), (1, 1000), (10, 100), (1, 0), (10, 0)]
            seconds, topics = 4.0, 2000
        rows = []
        for pairs, rate in matrix:
            direct = await pairs_run(directory, pairs, rate, seconds, routed=False)
            routed = await pairs_run(directory, pairs, rate, seconds, routed=True)
            log(
                f"{pairs} pair(s) at {rate or 'max'} Hz: direct {direct['msgs_per_s']:.0f}/s, "
                f"routed {routed['msgs_per_s']:.0f}/s, delivery {routed['delivery']:.4f}"
            )
            rows.append((direct, routed))
        switched = await switch_run(directory, 2.0 if args.quick else 4.0)
        log(f"switch: heard {switched['heard']}, lost {switched['lost']}, duplicated {switched['duplicated']}")
        mapped = await mapping_run(topics)
        log(
            f"mapping: {mapped['ms_per_topic']:.3f} ms per topic on average, {mapped['last_ms']:.3f} ms for the last"
            f" tenth, {mapped['move_ms']:.3f} ms to open a topic's cloud instances; {mapped['kb_per_topic']:.1f} KB"
        )
    ros1 = dict(ROS1)
    if args.ros1:
        command = [sys.executable, str(ROOT / "benchmarks" / "router.py"), "--quick"]
        done = await asyncio.to_thread(subprocess.run, command, capture_output=True, text=True)
        ros1.update(json.loads(done.stdout.strip().splitlines()[-1]))
    saturated = [(d, r) for d, r in rows if d["rate"] == 0]
    nominal = [(d, r) for d, r in rows if d["rate"] > 0]
    ratio = min(r["msgs_per_s"] / d["msgs_per_s"] for d, r in saturated if d["msgs_per_s"])
    delivery = min(r["delivery"] for _, r in nominal)
    added = statistics.median(r["p50_ms"] - d["p50_ms"] for d, r in nominal)
    out = sys.stderr
    print("\nSkill Router, ROS 2 (rclpy) beside ROS 1 (benchmarks/router.py) and the thesis (§5.4.1)", file=out)
    print(f"{'what':40} {'ROS 2':>10} {'ROS 1':>10} {'thesis':>10} {'goal':>8}", file=out)
    table = [
        ("routed / direct, flat out (min)", f"{ratio:.2f}", ros1["routed_over_direct"], "-", ">= 0.6"),
        ("delivery at nominal rates (min)", f"{delivery:.4f}", ros1["delivery_ratio"], THESIS["delivery_ratio"], "1.0"),
        ("added latency p50, ms", f"{added:.3f}", ros1["added_latency_p50_ms"], "-", "-"),
        ("switch under 1 kHz: lost / duplicated", f"{switched['lost']}/{switched['duplicated']}", "0/0", "-", "0/0"),
        (
            f"topic mapping at {topics} topics, ms",
            f"{mapped['last_ms']:.3f}",
            ros1["topic_map_ms"],
            THESIS["topic_map_ms"],
            "<= 10",
        ),
        ("  mean over all, ms", f"{mapped['ms_per_topic']:.3f}", "-", "-", "-"),
        ("  cloud instances opened, ms per topic", f"{mapped['move_ms']:.3f}", "-", "-", "-"),
        ("memory per topic, KB", f"{mapped['kb_per_topic']:.1f}", ros1["kb_per_topic"], THESIS["kb_per_topic"], "-"),
    ]
    for row in table:
        print(f"{row[0]:40} {row[1]:>10} {row[2]!s:>10} {row[3]:>10} {row[4]:>8}", file=out)
    print(
        f"\n{'pairs':>5} {'Hz':>6} {'direct/s':>10} {'routed/s':>10} {'ratio':>6} {'deliv':>7} {'p50 d/r ms':>14}",
        file=out,
    )
    for d, r in rows:
        print(
            f"{d['pairs']:>5} {d['rate'] or 'max':>6} {d['msgs_per_s']:>10.0f} {r['msgs_per_s']:>10.0f}"
            f" {r['msgs_per_s'] / max(d['msgs_per_s'], 1e-9):>6.2f} {r['delivery']:>7.4f}"
            f" {d['p50_ms']:>6.2f}/{r['p50_ms']:<7.2f}",
            file=out,
        )
    return {
        "routed_over_direct": round(ratio, 3),
        "delivery_ratio": round(delivery, 5),
        "switch_lost": switched["lost"],
        "switch_duplicated": switched["duplicated"],
        "added_latency_p50_ms": round(added, 3),
        "topic_map_ms": round(mapped["last_ms"], 3),
        "topic_map_mean_ms": round(mapped["ms_per_topic"], 3),
        "topic_move_ms": round(mapped["move_ms"], 3),
        "kb_per_topic": round(mapped["kb_per_topic"], 2),
        "topics_mapped": topics,
    }


if __name__ == "__main__":
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    parser = arguments(__doc__, "fewer pairs, rates and seconds (<1 min)")
    parser.add_argument("--ros1", action="store_true", help="also run benchmarks/router.py --quick for ROS 1's column")
    report(asyncio.run(main(parser.parse_args())))
