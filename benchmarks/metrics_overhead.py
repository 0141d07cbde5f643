"""What Prometheus instrumentation costs on the hot paths, with metrics on and off in the same run.

- ingest: metric frames of 100 points decoded, counted and written by the cloud's real
  MetricWriter (COPY into PostgreSQL) in this process, as a robot consumer does; the cost
  is this process's CPU seconds per point (the database server's work is the same either
  way), metrics on (prometheus_client multiprocess mode, as daphne runs it) vs off (the
  recording calls replaced by no-ops). Goal: overhead <= 3 %.
- router: the agent's SkillRouter routing 10 rospy publisher/subscriber pairs flat out
  (real rosmaster and rospy nodes, as benchmarks/router.py), the agent's /metrics served
  from the router's event loop; windows where it is scraped every 0.5 s (30x Prometheus'
  default rate) alternate with windows where it is not; the overhead is the routed msgs/s
  lost in scraped windows (CPU per message is reported beside it). Goal <= 3 %.
- scrape: a real daphne's /metrics over HTTP with 1,000 robots in PostgreSQL (their
  connected and last-seen series read at scrape time). Goal <= 50 ms.

Off and on run back to back in pairs (order alternating), so load from elsewhere on the machine
falls on both; an overhead is the median of the pairs' ratios.

    .venv/bin/python benchmarks/metrics_overhead.py --quick
    .venv/bin/python benchmarks/metrics_overhead.py

The last line is one JSON object: ingest_overhead_pct, router_overhead_pct, scrape_ms, and the details.
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import os
import statistics
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from typing import TYPE_CHECKING

from _common import Daphne, ensure_postgres_database, free_port, log, migrate, setup_django

if TYPE_CHECKING:
    from monitoring.ingest import MetricWriter

POINTS_PER_FRAME = 100
ROBOTS = 1000


# ---------------------------------------------------------------------- ingest


class _NullGauge:
    def set(self, value: float) -> None:
        pass


def _metrics_switch():
    """Return a function that turns the cloud's recording calls on or off."""
    from monitoring import prometheus

    real = {
        name: getattr(prometheus, name)
        for name in ("frame_received", "points_received", "batch_written", "copy_failed", "INGEST_PENDING_ROWS")
    }

    def nothing(*args: object, **kw: object) -> None:
        return None

    def switch(on: bool) -> None:
        for name, value in real.items():
            if on:
                setattr(prometheus, name, value)
            elif name == "INGEST_PENDING_ROWS":
                setattr(prometheus, name, _NullGauge())
            else:
                setattr(prometheus, name, nothing)

    return switch


def ingest_frames(count: int, robots: list[str]) -> list[tuple[str, str]]:
    """Encode ``count`` metrics frames of 100 points, spread over the robots."""
    from bridgeos_agent import protocol
    from bridgeos_agent.protocol import Event

    frames = []
    base = time.time() - 3600
    for n in range(count):
        points = [
            {"name": f"m{i % 10}", "value": (n * i) % 97 / 7, "ts": base + n * 0.01 + i * 1e-4, "component": "c"}
            for i in range(POINTS_PER_FRAME)
        ]
        frames.append(
            (robots[n % len(robots)], protocol.encode(protocol.make(Event.METRICS, {"metrics": points}, now=base)))
        )
    return frames


async def ingest_round(writer: MetricWriter, frames: list[tuple[str, str]]) -> float:
    """Decode, count and write every frame as the robot consumer does; return CPU seconds per point."""
    from bridgeos_agent import protocol
    from monitoring import prometheus

    futures = []
    cpu = time.process_time()
    for n, (robot_id, text) in enumerate(frames):
        envelope = protocol.decode(text, direction=protocol.Direction.ROBOT_TO_CLOUD)
        prometheus.frame_received()
        points = protocol.parse_payload(envelope).metrics
        prometheus.points_received(len(points))
        futures.append(writer.add(robot_id, points))
        if n % 20 == 19:
            await asyncio.sleep(0)  # let the flusher run, as daphne's loop would between frames
    await asyncio.gather(*futures)
    return (time.process_time() - cpu) / (len(frames) * POINTS_PER_FRAME)


async def measure_ingest(frames: list[tuple[str, str]], pairs: int) -> dict:
    """Run off/on rounds back to back through one writer; the overhead is the median of the pairs' ratios."""
    from monitoring import prometheus
    from monitoring.ingest import MetricWriter

    switch = _metrics_switch()
    writer = MetricWriter(flush_rows=5000, flush_interval=0.05)
    writer.start()
    await ingest_round(writer, frames)  # warm up: the connection, caches
    ratios, offs, ons = [], [], []
    for n in range(pairs):
        cost = {}
        for on in (False, True) if n % 2 == 0 else (True, False):
            switch(on)
            gc.collect()
            cost[on] = await ingest_round(writer, frames)
        ratios.append(cost[True] / cost[False])
        offs.append(cost[False])
        ons.append(cost[True])
    switch(True)
    await writer.close()
    # The recording calls alone, per frame, for scale: two counters per frame (the batch's are per flush).
    calls = 100_000
    started = time.process_time()
    for _ in range(calls):
        prometheus.frame_received()
        prometheus.points_received(POINTS_PER_FRAME)
    per_frame_us = (time.process_time() - started) / calls * 1e6
    off, on = statistics.median(offs), statistics.median(ons)
    log(f"ingest: {1 / off:,.0f} points per CPU second off, {1 / on:,.0f} on; recording {per_frame_us:.2f} µs/frame")
    return {
        "ingest_points_per_cpu_s_off": round(1 / off),
        "ingest_points_per_cpu_s_on": round(1 / on),
        "ingest_overhead_pct": round((statistics.median(ratios) - 1) * 100, 2),
        "ingest_recording_us_per_frame": round(per_frame_us, 2),
        "ingest_recording_pct_of_frame": round(per_frame_us / (off * POINTS_PER_FRAME * 1e6) * 100, 2),
    }


# ---------------------------------------------------------------------- router


async def measure_router(pairs: int, windows: int, window_s: float) -> dict:
    """Route flat-out pairs through one router; alternate windows with /metrics scraped or not."""
    import aiohttp
    from router import PUB_NS, Pairs, rosmaster, skill_config
    from router import settings as router_settings

    from bridgeos_agent import metrics
    from bridgeos_agent.outbox import Outbox
    from bridgeos_agent.router import SkillRouter

    home = tempfile.mkdtemp(prefix="bench-metrics-router-")
    seconds = windows * 2 * window_s + 3
    with rosmaster(home) as master:
        sub = await Pairs.start(master, home, "sub", pairs, 0, seconds, sample=1000)
        router = SkillRouter(skill_config(pairs, subscriber=False), ros_master=master, settings=router_settings())
        router.set_active("pub", "robot")
        await router.start()
        outbox = Outbox(Path(home) / "outbox.sqlite3")
        link = asyncio.Event()
        link.set()
        collector = metrics.AgentCollector(metrics.AgentMetrics("bench"), outbox, link, lambda: [("bench", router)])
        address = f"127.0.0.1:{free_port()}"
        exporter = await metrics.serve(collector, address)
        scraping = asyncio.Event()
        scrapes: list[float] = []

        async def scrape_while_asked() -> None:
            async with aiohttp.ClientSession() as session:
                while True:
                    await scraping.wait()
                    started = time.perf_counter()
                    async with session.get(f"http://{address}/metrics") as answer:
                        await answer.read()
                    scrapes.append((time.perf_counter() - started) * 1000)
                    await asyncio.sleep(0.5)

        def routed() -> int:
            return sum(figures["messages"] for figures in router.statistics().values() if figures["kind"] == "topic")

        scraper = asyncio.create_task(scrape_while_asked())
        pub = await Pairs.start(master, home, "pub", pairs, 0, seconds, prefix="bench", namespace=PUB_NS)
        ratios, rates, cpu_per_msg = [], {False: [], True: []}, {False: [], True: []}
        try:
            await sub.wait_for("ready", 60)
            await pub.wait_for("ready", 120)
            deadline = time.monotonic() + 60
            while not all(router.node.publications[f"/bench{n}/data"].connections for n in range(pairs)):
                if time.monotonic() > deadline:
                    raise RuntimeError("the subscribers never connected to the router")
                await asyncio.sleep(0.05)
            pub.tell()
            await asyncio.sleep(1.0)  # past the start-up
            for n in range(windows):
                cost = {}
                for on in (False, True) if n % 2 == 0 else (True, False):
                    if on:
                        scraping.set()
                    else:
                        scraping.clear()
                    await asyncio.sleep(0.05)  # a scrape under way finishes in its own window
                    cpu, messages, started = time.process_time(), routed(), time.monotonic()
                    await asyncio.sleep(window_s)
                    sent = routed() - messages
                    rate = sent / (time.monotonic() - started)
                    cost[on] = rate
                    rates[on].append(rate)
                    cpu_per_msg[on].append((time.process_time() - cpu) / max(sent, 1))
                # Throughput lost to scraping: 1 - rate with scrapes / rate without.
                ratios.append(cost[False] / cost[True])
            scraping.clear()
        finally:
            scraper.cancel()
            await exporter.cleanup()
            await pub.stop()
            await sub.stop()
            await router.close()
            outbox.close()
    off, on = statistics.median(rates[False]), statistics.median(rates[True])
    log(f"router: {off:,.0f} msg/s without scrapes, {on:,.0f} with a scrape every 0.5 s")
    return {
        "router_msgs_per_s_off": round(off),
        "router_msgs_per_s_on": round(on),
        "router_overhead_pct": round((statistics.median(ratios) - 1) * 100, 2),
        "router_cpu_us_per_msg_off": round(statistics.median(cpu_per_msg[False]) * 1e6, 3),
        "router_cpu_us_per_msg_on": round(statistics.median(cpu_per_msg[True]) * 1e6, 3),
        "agent_scrape_ms": round(statistics.median(scrapes), 2) if scrapes else None,
    }


# ---------------------------------------------------------------------- scrape


def fleet_of(count: int) -> list[str]:
    """Make sure ``count`` benchmark robots exist, about half of them connected; return their ids."""
    from django.contrib.auth import get_user_model
    from django.utils import timezone

    from robots.models import Robot

    owner, _ = get_user_model().objects.get_or_create(username="bench-metrics")
    ids = [f"bench-metrics-{n:04d}" for n in range(count)]
    existing = set(Robot.objects.filter(id__in=ids).values_list("id", flat=True))
    Robot.objects.bulk_create(
        [
            Robot(id=robot_id, owner=owner, connected=n % 2 == 0, last_seen=timezone.now(), token_hash="x" * 64)
            for n, robot_id in enumerate(ids)
            if robot_id not in existing
        ]
    )
    return ids


def measure_scrape(env: dict[str, str], data_dir: Path, scrapes: int) -> dict:
    daphne = Daphne(env, data_dir / "daphne.log")
    try:
        daphne.wait()
        url = f"http://127.0.0.1:{daphne.port}/metrics"
        urllib.request.urlopen(url, timeout=10).read()  # warm up: imports, the database connection
        times, size = [], 0
        for _ in range(scrapes):
            started = time.perf_counter()
            body = urllib.request.urlopen(url, timeout=10).read()
            times.append((time.perf_counter() - started) * 1000)
            size = len(body)
        series = sum(1 for line in body.decode().splitlines() if line and not line.startswith("#"))
    finally:
        daphne.stop()
    log(f"scrape: {statistics.median(times):.1f} ms median of {scrapes}, {series} series, {size / 1024:.0f} KiB")
    return {"scrape_ms": round(statistics.median(times), 2), "scrape_series": series, "scrape_kib": round(size / 1024)}


# ---------------------------------------------------------------------- main


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="fewer and shorter rounds: under a minute")
    parser.add_argument("--database-url", default="postgres://postgres@127.0.0.1:5432/bridgeos_bench_metrics")
    parser.add_argument("--skip-router", action="store_true", help="no ROS here: measure ingest and scrape only")
    args = parser.parse_args()
    ingest_pairs, frames_per_round, router_windows, window_s, scrapes = (
        (12, 300, 8, 1.0, 20) if args.quick else (40, 600, 30, 1.0, 100)
    )

    data_dir = Path(tempfile.mkdtemp(prefix="bridgeos-bench-metrics-"))
    env = {"DATABASE_URL": args.database_url, "BRIDGEOS_DATA_DIR": str(data_dir), "REDIS_URL": ""}
    ensure_postgres_database(args.database_url)
    migrate(env)
    setup_django(env)
    robots = fleet_of(ROBOTS)
    log(f"{len(robots)} robots; prometheus multiprocess dir {os.environ.get('PROMETHEUS_MULTIPROC_DIR')}")

    result: dict = {}
    result.update(asyncio.run(measure_ingest(ingest_frames(frames_per_round, robots[:100]), ingest_pairs)))
    if args.skip_router:
        result["router_overhead_pct"] = None
    else:
        result.update(asyncio.run(measure_router(10, router_windows, window_s)))
    result.update(measure_scrape(env, data_dir, scrapes))

    print("\nPrometheus instrumentation (issue 21)", file=sys.stderr)
    print(f"{'what':44} {'here':>12} {'goal':>10}", file=sys.stderr)
    print(f"{'ingest overhead, % CPU per point':44} {result['ingest_overhead_pct']:>12} {'<= 3':>10}", file=sys.stderr)
    print(
        f"{'router overhead, % msgs/s lost to scrapes':44} {result['router_overhead_pct']!s:>12} {'<= 3':>10}",
        file=sys.stderr,
    )
    print(f"{'cloud scrape with 1,000 robots, ms':44} {result['scrape_ms']:>12} {'<= 50':>10}", file=sys.stderr)
    print(json.dumps(result))


if __name__ == "__main__":
    main()
