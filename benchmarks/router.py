"""The Skill Router (thesis §5.4.1, Figures 5.9-5.10): topic mapping, routed vs direct rospy, memory.

Runs a private rosmaster, real rospy publishers and subscribers (Debian's /usr/bin/python3)
and the agent's SkillRouter in this process:

- mapping: a fresh router maps 1..N topics (each with a movable publisher and a movable
  subscriber: 6 registrations a topic); time per topic (thesis 443 +- 20 ms, 5000 topics;
  goal <=10 ms and 20,000 topics);
- throughput: P publisher/subscriber pairs at R Hz (0 = as fast as they go), first direct
  rospy to rospy, then the same through the router (publishers in a component's robot
  namespace, subscribers on the canonical names), in the same run: messages/s, routed/direct,
  delivery ratio (thesis 98.42 %), added latency p50/p99 (goals >=60 % of direct, 100 %
  delivery at nominal load, <=0.5 ms added p50; thesis 50,000 msg/s on an 8-thread server);
- memory: what one router and each topic add to the agent process, by tracemalloc (thesis
  46.47 MB per router process, 10 KB per topic; goal <=5 MB, <=2 KB).

    .venv/bin/python benchmarks/router.py --quick
    .venv/bin/python benchmarks/router.py

The last line is one JSON object with the figures.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import gc
import json
import signal
import statistics
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ROOT, log, percentile
from _harness import HOST_PYTHON, arguments, machine_load, report, ros_env, rosmaster

from bridgeos_agent.router import RouterSettings, SkillRouter
from bridgeos_agent.skillconfig import parse_skill_config

NODES = str(ROOT / "tests" / "agent" / "rosnodes.py")
SKILL = "bench"
PUB_NS = f"/bridgeos/{SKILL}/pub/robot"


def skill_config(topics: int, *, subscriber: bool = True, prefix: str = "bench"):
    """Return a Skill of one movable publisher and one movable subscriber sharing ``topics`` topics."""
    spec = {"command": ["true"]}
    components = {
        "pub": {"name": "Pub", "location": "either", "robot": spec, "cloud": spec},
        "sub": {"name": "Sub", "location": "either", "robot": spec, "cloud": spec},
    }
    routes = [
        {
            "name": f"/{prefix}{n}/data",
            "type": "std_msgs/String",
            "publisher": "pub",
            "subscribers": ["sub"] if subscriber else [],
        }
        for n in range(topics)
    ]
    return parse_skill_config(
        {"skill": "Bench", "skill_id": SKILL, "components": components, "router": {"topics": routes}}
    )


def settings() -> RouterSettings:
    return RouterSettings(http_host="127.0.0.1", statistics_period=1.0)


# ---------------------------------------------------------------------- mapping


async def mapping(master: str, counts: list[int]) -> list[dict]:
    """Time a fresh router mapping each number of topics."""
    rows = []
    for count in counts:
        config = skill_config(count)
        router = SkillRouter(config, ros_master=master, settings=settings())
        router.set_active("pub", "robot")
        router.set_active("sub", "robot")
        started = time.perf_counter()
        await router.start()
        elapsed = time.perf_counter() - started
        ok = router.ros_on and len(router._topics) == count and len(router.node.publications) == 3 * count + 1
        await router.close()
        rows.append({"topics": count, "seconds": round(elapsed, 3), "ms_per_topic": elapsed * 1000 / count, "ok": ok})
        log(f"mapping: {count} topics in {elapsed:.2f} s, {elapsed * 1000 / count:.2f} ms per topic, ok={ok}")
    return rows


# ---------------------------------------------------------------------- memory


async def memory(master: str, count: int) -> dict:
    """Measure what one router and each of its topics add to this process's Python heap."""
    # The Skill configs live in the controller whether or not a router runs: build them first.
    one_config, many_config = skill_config(1, prefix="one"), skill_config(count, prefix="many")
    gc.collect()
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    one = SkillRouter(one_config, ros_master=master, settings=settings())
    await one.start()
    gc.collect()
    with_one = tracemalloc.get_traced_memory()[0]
    many = SkillRouter(
        many_config.model_copy(update={"skill_id": "bench-many"}), ros_master=master, settings=settings()
    )
    await many.start()
    gc.collect()
    with_many = tracemalloc.get_traced_memory()[0]
    tracemalloc.stop()
    await many.close()
    await one.close()
    router_mb = (with_one - before) / 2**20
    kb_per_topic = (with_many - with_one - (with_one - before)) / (count - 1) / 1024
    log(f"memory: one router with one topic {router_mb:.3f} MB; {kb_per_topic:.2f} KB per topic over {count} topics")
    return {"router_mb": router_mb, "kb_per_topic": kb_per_topic, "topics": count}


# ---------------------------------------------------------------------- throughput


class Pairs:
    """One rospy process of publishers or subscribers (tests/agent/rosnodes.py pairs)."""

    def __init__(self, process: asyncio.subprocess.Process) -> None:
        self.process = process

    @classmethod
    async def start(cls, master: str, home: str, mode: str, pairs: int, rate: float, seconds: float, **kw) -> Pairs:
        argv = [NODES, "pairs", "--mode", mode, "--pairs", str(pairs), "--rate", str(rate), "--seconds", str(seconds)]
        argv += ["--prefix", kw.get("prefix", "/bench"), "--sample", str(kw.get("sample", 1))]
        process = await asyncio.create_subprocess_exec(
            HOST_PYTHON,
            *argv,
            env=ros_env(master, home, kw.get("namespace")),
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.DEVNULL,
            start_new_session=True,
            limit=1 << 24,  # the subscribers' summary is one long JSON line
        )
        return cls(process)

    async def line(self, timeout: float) -> str:
        raw = await asyncio.wait_for(self.process.stdout.readline(), timeout)
        if not raw:
            raise RuntimeError("a rospy benchmark node ended early")
        return raw.decode().strip()

    async def wait_for(self, word: str, timeout: float) -> str:
        while True:
            text = await self.line(timeout)
            if text.startswith(word):
                return text

    def tell(self) -> None:
        self.process.stdin.write(b"go\n")

    async def stop(self) -> None:
        if self.process.returncode is None:
            self.process.kill()
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self.process.communicate(), 30)


async def one_run(master: str, home: str, pairs: int, rate: float, seconds: float, routed: bool) -> dict:
    """Publish for ``seconds`` over ``pairs`` pairs at ``rate`` Hz, directly or through a router."""
    router = None
    sample = max(1, round(pairs * (rate or 10000) * seconds / 5000))  # about 5000 latency samples
    sub = await Pairs.start(master, home, "sub", pairs, rate, seconds, sample=sample)
    try:
        if routed:
            router = SkillRouter(skill_config(pairs, subscriber=False), ros_master=master, settings=settings())
            router.set_active("pub", "robot")
            await router.start()
            pub = await Pairs.start(master, home, "pub", pairs, rate, seconds, prefix="bench", namespace=PUB_NS)
        else:
            pub = await Pairs.start(master, home, "pub", pairs, rate, seconds)
        try:
            await sub.wait_for("ready", 60)
            await pub.wait_for("ready", 120)
            if router is not None:  # every subscriber connected to the router's canonical publication
                deadline = time.monotonic() + 60
                while not all(router.node.publications[f"/bench{n}/data"].connections for n in range(pairs)):
                    if time.monotonic() > deadline:
                        raise RuntimeError("the subscribers never connected to the router")
                    await asyncio.sleep(0.05)
            started = time.monotonic()
            pub.tell()
            sent = json.loads(await pub.wait_for("{", seconds + 120))["sent"]
            elapsed = time.monotonic() - started
            await asyncio.sleep(1.0)  # let the last messages arrive
            sub.tell()
            stats = json.loads(await sub.wait_for("{", 60))
        finally:
            await pub.stop()
    finally:
        await sub.stop()
        if router is not None:
            dropped = router.statistics()
            await router.close()
    received = stats["received"]
    latencies = sorted(stats["latencies"])
    row = {
        "pairs": pairs,
        "rate": rate,
        "routed": routed,
        "sent": sent,
        "received": received,
        "msgs_per_s": received / elapsed,
        "delivery": received / sent if sent else 1.0,
        "p50_ms": (percentile(latencies, 50) or 0) * 1000,
        "p99_ms": (percentile(latencies, 99) or 0) * 1000,
    }
    if router is not None:
        row["router_dropped"] = sum(t["dropped"] for t in dropped.values())
    log(
        f"  {'routed' if routed else 'direct'} {pairs} pair(s) at {rate or 'max'} Hz: {row['msgs_per_s']:.0f} msg/s,"
        f" delivery {row['delivery']:.4f}, p50 {row['p50_ms']:.2f} ms, p99 {row['p99_ms']:.2f} ms"
    )
    return row


async def throughput(master: str, home: str, matrix: list[tuple[int, float]], seconds: float) -> list[dict]:
    rows = []
    for pairs, rate in matrix:
        direct = await one_run(master, home, pairs, rate, seconds, routed=False)
        routed = await one_run(master, home, pairs, rate, seconds, routed=True)
        rows.append({"direct": direct, "routed": routed})
    return rows


# ---------------------------------------------------------------------- main


async def main(args: argparse.Namespace) -> dict:
    home = tempfile.mkdtemp(prefix="bench-router-")
    log(f"machine: {machine_load()}")
    with rosmaster(home) as master:
        counts = [1, 10, 100, 1000, 2000] if args.quick else [1, 10, 100, 1000, 5000, 10000, 20000]
        mapped = await mapping(master, counts)
    with rosmaster(home) as master:
        mem = await memory(master, 2000 if args.quick else 20000)
    with rosmaster(home) as master:
        if args.quick:
            matrix, seconds = [(1, 1000), (10, 100), (1, 0), (10, 0)], 2.0
        else:
            matrix = [(p, r) for p in (1, 10, 100) for r in (1, 100, 500, 1000)] + [(1, 0), (10, 0)]
            seconds = 10.0
        rows = await throughput(master, home, matrix, seconds)
    log(f"machine after: {machine_load()}")

    largest = max((row for row in mapped if row["ok"]), key=lambda row: row["topics"])
    nominal = [row for row in rows if row["direct"]["rate"] > 0]
    saturated = [row for row in rows if row["direct"]["rate"] == 0]
    ratio = min(row["routed"]["msgs_per_s"] / row["direct"]["msgs_per_s"] for row in saturated)
    delivery = min(row["routed"]["delivery"] for row in nominal)
    added = statistics.median(row["routed"]["p50_ms"] - row["direct"]["p50_ms"] for row in nominal)
    added_p99 = statistics.median(row["routed"]["p99_ms"] - row["direct"]["p99_ms"] for row in nominal)

    print("\nSkill Router (thesis Figures 5.9-5.10)", file=sys.stderr)
    print(f"{'what':44} {'here':>14} {'thesis':>14} {'goal':>12}", file=sys.stderr)
    print(
        f"{'topic mapping, ms per topic (' + str(largest['topics']) + ' topics)':44}"
        f" {largest['ms_per_topic']:>14.3f} {'443 +- 20':>14} {'<= 10':>12}",
        file=sys.stderr,
    )
    print(f"{'topics mapped by one router':44} {largest['topics']:>14} {5000:>14} {20000:>12}", file=sys.stderr)
    print(
        f"{'router memory in the agent, MB':44} {mem['router_mb']:>14.3f} {'46.47 +- 1.3':>14} {'<= 5':>12}",
        file=sys.stderr,
    )
    print(f"{'memory per topic, KB':44} {mem['kb_per_topic']:>14.2f} {10:>14} {'<= 2':>12}", file=sys.stderr)
    print(f"{'routed / direct throughput (saturated)':44} {ratio:>14.2f} {'-':>14} {'>= 0.6':>12}", file=sys.stderr)
    print(f"{'delivery ratio at nominal load (min)':44} {delivery:>14.4f} {'0.9842':>14} {'1.0':>12}", file=sys.stderr)
    print(f"{'added latency p50, ms (median)':44} {added:>14.3f} {'-':>14} {'<= 0.5':>12}", file=sys.stderr)
    print(f"{'added latency p99, ms (median)':44} {added_p99:>14.3f} {'-':>14} {'-':>12}", file=sys.stderr)
    best = max(row["routed"]["msgs_per_s"] for row in rows)
    print(f"{'best routed msg/s':44} {best:>14.0f} {'50000 (8 thr)':>14} {'-':>12}", file=sys.stderr)
    header = f"{'pairs':>5} {'Hz':>6} {'direct/s':>10} {'routed/s':>10} {'ratio':>6} {'deliv':>7}"
    print(f"\n{header} {'p50 d/r ms':>14} {'p99 d/r ms':>14}", file=sys.stderr)
    for row in rows:
        d, r = row["direct"], row["routed"]
        print(
            f"{d['pairs']:>5} {d['rate'] or 'max':>6} {d['msgs_per_s']:>10.0f} {r['msgs_per_s']:>10.0f}"
            f" {r['msgs_per_s'] / d['msgs_per_s']:>6.2f} {r['delivery']:>7.4f}"
            f" {d['p50_ms']:>6.2f}/{r['p50_ms']:<7.2f} {d['p99_ms']:>6.2f}/{r['p99_ms']:<7.2f}",
            file=sys.stderr,
        )
    return {
        "topic_map_ms": round(largest["ms_per_topic"], 3),
        "max_topics": largest["topics"],
        "routed_over_direct": round(ratio, 3),
        "delivery_ratio": round(delivery, 5),
        "added_latency_p50_ms": round(added, 3),
        "added_latency_p99_ms": round(added_p99, 3),
        "routed_msgs_per_s_best": round(best),
        "router_mb": round(mem["router_mb"], 3),
        "kb_per_topic": round(mem["kb_per_topic"], 3),
    }


if __name__ == "__main__":
    # A terminated run still stops its rosmaster and rospy nodes (they run in sessions of their own).
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    parser = arguments(__doc__, "fewer topics, pairs and seconds (<1 min)")
    report(asyncio.run(main(parser.parse_args())))
