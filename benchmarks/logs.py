"""Component logs end to end: a real agent's component prints, the cloud stores, a live tail reads.

- tail: a component prints a line carrying its own clock 20 times a second; a client of the
  cloud's /ws/client/ subscribed with `logs_subscribe` receives it: `tail_p95_ms` is printed
  to received (goal <= 250).
- flood: the same robot's component prints 50,000 lines/s; `lines_per_s_stored` is the lines
  the cloud stored per second over the window (goal >= 20,000; the robot's default cap is
  25,000 lines/s, the rest is dropped and counted). Meanwhile the robot's own metrics are
  timed from their sample to a live client:
  `metrics_lag_under_flood_over_quiet` is their median lag under the flood over the median
  lag of the quiet window before it, in the same run (goal <= 1.2).
- query: one million lines stored (written server-side), then `GET /api/robot/<id>/logs?q=`
  for a word in a handful of them, through a real daphne: `query_1m_lines_ms` is the median
  of several (goal <= 500).
- cli: `bridgeos --help` wall time, median of several runs (goal <= 300).

    .venv/bin/python benchmarks/logs.py --quick
    .venv/bin/python benchmarks/logs.py

The last line is one JSON object: lines_per_s_stored, tail_p95_ms,
metrics_lag_under_flood_over_quiet, query_1m_lines_ms, cli_start_ms, and the details.
"""

from __future__ import annotations

import asyncio
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import log, percentile
from _harness import Cloud, arguments, cloud, machine_load, report

ROBOT = "bench-logs-0"
OWNER = "bench-logs-owner"
SKILL = "chatter"
TAIL_RATE = 20  # lines/s of the tail window
FLOOD_RATE = 50_000  # lines/s of the flood (the issue's)
QUERY_LINES = 1_000_000
NEEDLE = "needle-7f3a"

# Prints "tail <its clock>" TAIL_RATE times a second until the flag file appears; then floods at
# FLOOD_RATE lines/s (blocks of 1,000 numbered lines) until the stop file appears; then idles.
CHATTER = r"""
import os, sys, time
flag, stop, rate, flood = sys.argv[1], sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
out = sys.stdout
while not os.path.exists(flag):
    out.write(f"[INFO] tail {time.time():.6f}\n"); out.flush()
    time.sleep(1 / rate)
n, began = 0, time.monotonic()
while not os.path.exists(stop):
    block = "".join(f"[INFO] flood line {n + i} of a chatty component, padded to a usual length\n" for i in range(1000))
    out.write(block); out.flush()
    n += 1000
    time.sleep(max(0.0, began + n / flood - time.monotonic()))
while True:
    time.sleep(1)
"""


def setup_fleet(flag: Path, stop: Path) -> dict[str, str]:
    """Create the owner, its robot with the chatty Skill, and an API token; return the tokens."""
    from django.contrib.auth import get_user_model

    from robots.models import Robot
    from robots.services import create_robot, issue_api_token
    from skills.services import add_skill

    User = get_user_model()
    Robot.objects.filter(id=ROBOT).delete()
    User.objects.filter(username=OWNER).delete()
    owner = User.objects.create_user(OWNER)
    robot, robot_token = create_robot(ROBOT, owner)
    command = [sys.executable, "-u", "-c", CHATTER, str(flag), str(stop), str(TAIL_RATE), str(FLOOD_RATE)]
    component = {"name": "talk", "location": "robot", "ros": False, "resources": {"cpu": 0.1, "ram": 32}}
    add_skill(
        robot,
        {"skill": "Chatter", "skill_id": SKILL, "components": {"talk": {**component, "robot": {"command": command}}}},
    )
    key, _ = issue_api_token(owner)
    return {"robot": robot_token, "api": key}


class LiveClient:
    """One /ws/client/ connection: metric lags and tail lags as they arrive, and log lines counted."""

    def __init__(self, url: str, token: str) -> None:
        self.url, self.token = url, token
        self.metric_lags: list[tuple[float, float]] = []  # (arrived, lag s)
        self.tail_lags: list[float] = []
        self.lines = 0
        self.dropped = 0

    async def run(self, ready: asyncio.Event) -> None:
        import websockets

        async with websockets.connect(f"{self.url}/ws/client/", max_size=None) as ws:
            await ws.send(json.dumps({"event": "authentication_client", "id": "auth-1", "data": {"token": self.token}}))
            answer = json.loads(await ws.recv())
            if answer["event"] != "authentication_success":
                raise RuntimeError(f"the live client was refused: {answer}")
            subscribe = {"robot": ROBOT, "skill": SKILL, "component": "talk", "tail": 0}
            await ws.send(json.dumps({"event": "logs_subscribe", "id": "tail-1", "data": subscribe}))
            ready.set()
            async for raw in ws:
                arrived = time.time()
                frame = json.loads(raw)
                data = frame.get("data") or {}
                if frame["event"] == "metrics" and data.get("robot") == ROBOT:
                    stamps = [p["ts"] for p in data.get("metrics", []) if p.get("component") is None]
                    if stamps:
                        self.metric_lags.append((arrived, arrived - max(stamps)))
                elif frame["event"] == "component_logs" and frame.get("reply_to") is None:
                    self.lines += len(data["lines"])
                    self.dropped += data.get("dropped", 0)
                    for line in data["lines"]:
                        if line["text"].startswith("[INFO] tail "):
                            self.tail_lags.append(arrived - float(line["text"].split()[2]))
                elif frame["event"] == "error_message":
                    raise RuntimeError(f"the cloud refused the live client: {data}")

    def lags_between(self, start: float, end: float) -> list[float]:
        return [lag for arrived, lag in self.metric_lags if start <= arrived < end]


def stored_lines() -> int:
    """Count the lines the cloud stored for the bench robot."""
    from logs.models import ComponentLog

    return ComponentLog.objects.filter(robot_id=ROBOT).count()


async def agent_run(bench: Cloud, tokens: dict[str, str], flag: Path, stop: Path, quick: bool) -> dict[str, Any]:
    """Tail, then flood; return the live figures."""
    import httpx
    from asgiref.sync import sync_to_async

    daphne = bench.daphnes[0]
    # Its flooding component goes with it: an agent keeps its components for the next one by default.
    flags = ("--simulate", "--sample-interval", "0.25", "--stop-components-on-exit", "-q")
    bench.start_agent(daphne, ROBOT, tokens["robot"], *flags)
    client = LiveClient(daphne.ws_url, tokens["api"])
    ready = asyncio.Event()
    listening = asyncio.create_task(client.run(ready))
    await asyncio.wait_for(ready.wait(), 30)
    headers = {"Authorization": f"Token {tokens['api']}"}
    async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{daphne.port}", headers=headers, timeout=30) as http:
        for _ in range(200):
            robot = (await http.get(f"/api/robot/{ROBOT}")).json()
            if robot.get("connected"):
                break
            await asyncio.sleep(0.1)
        else:
            raise RuntimeError(f"the agent did not connect: {robot}")
        started = await http.post(f"/api/robot/{ROBOT}/skill/{SKILL}/start", json={})
        if started.status_code >= 300:
            raise RuntimeError(f"the Skill did not start: {started.status_code} {started.text}")
    window = 8 if quick else 30
    # Quiet: the component prints its tail lines only.
    for _ in range(300):
        if client.tail_lags:
            break
        await asyncio.sleep(0.1)
    else:
        raise RuntimeError("no tail line reached the live client in 30 s")
    quiet_start = time.time()
    await asyncio.sleep(window)
    quiet_end = time.time()
    tail_lags = list(client.tail_lags)
    # Flood.
    before = await sync_to_async(stored_lines)()
    await asyncio.to_thread(flag.touch)
    await asyncio.sleep(2)  # the flood under way
    flood_start, stored_start = time.time(), await sync_to_async(stored_lines)()
    await asyncio.sleep(window)
    flood_end, stored_end = time.time(), await sync_to_async(stored_lines)()
    await asyncio.to_thread(stop.touch)
    listening.cancel()
    quiet = client.lags_between(quiet_start, quiet_end)
    flood = client.lags_between(flood_start, flood_end)
    if not quiet or not flood:
        raise RuntimeError(f"too few metric samples: {len(quiet)} quiet, {len(flood)} under the flood")
    figures = {
        "tail_p95_ms": round((percentile(tail_lags, 95) or 0) * 1000, 1),
        "tail_p50_ms": round((percentile(tail_lags, 50) or 0) * 1000, 1),
        "tail_lines": len(tail_lags),
        "lines_per_s_stored": round((stored_end - stored_start) / (flood_end - flood_start)),
        "lines_stored_before_flood": before,
        "live_lines_received": client.lines,
        "live_dropped_reported": client.dropped,
        "metrics_lag_quiet_ms": round(statistics.median(quiet) * 1000, 1),
        "metrics_lag_flood_ms": round(statistics.median(flood) * 1000, 1),
        "metrics_samples": [len(quiet), len(flood)],
    }
    figures["metrics_lag_under_flood_over_quiet"] = round(
        figures["metrics_lag_flood_ms"] / max(figures["metrics_lag_quiet_ms"], 0.1), 2
    )
    return figures


def fill_million(robot_id: str) -> None:
    """Write QUERY_LINES lines of one robot server-side, a few carrying NEEDLE, over the last day."""
    from django.db import connection
    from django.utils import timezone

    from logs import partitions
    from logs.models import ComponentLog

    table = ComponentLog._meta.db_table
    now = timezone.now()
    partitions.ensure_partitions(now)  # yesterday's and today's
    with connection.cursor() as cursor:
        cursor.execute(f"DELETE FROM {table} WHERE robot_id = %s", [robot_id])
        # Server-side: no row crosses the socket. Every 200,000th line carries the needle.
        cursor.execute(
            f"INSERT INTO {table} (robot_id, skill, component, location, seq, ts, stream, level, text)"
            " SELECT %s, 'bulk', 'c' || (g %% 4), 'robot', g, %s - (interval '1 second' * 86000.0 / %s) * (%s - g),"
            " 'stdout', CASE WHEN g %% 10 = 0 THEN 2 ELSE 1 END,"
            " CASE WHEN g %% 200000 = 7 THEN 'found the ' || %s || ' at ' || g"
            " ELSE '[INFO] processed frame ' || g || ' in ' || (g %% 97) || ' ms, queue ' || (g %% 13) END"
            " FROM generate_series(1, %s) g",
            [robot_id, now, QUERY_LINES, QUERY_LINES, NEEDLE, QUERY_LINES],
        )
        cursor.execute(f"ANALYZE {table}")


async def query_run(bench: Cloud, tokens: dict[str, str], quick: bool) -> dict[str, Any]:
    """Time text queries over a million stored lines through the REST API."""
    import httpx
    from asgiref.sync import sync_to_async

    started = time.monotonic()
    await sync_to_async(fill_million)(ROBOT)
    log(f"query: {QUERY_LINES:,} lines written in {time.monotonic() - started:.1f} s")
    daphne = bench.daphnes[0]
    headers = {"Authorization": f"Token {tokens['api']}"}
    timings: dict[str, list[float]] = {"substring": [], "regex": []}
    params = {"substring": {"q": NEEDLE}, "regex": {"q": NEEDLE + r" at \d+", "regex": "true"}}
    async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{daphne.port}", headers=headers, timeout=60) as http:
        for kind, query in params.items():
            for _ in range(3 if quick else 7):
                began = time.perf_counter()
                answer = await http.get(f"/api/robot/{ROBOT}/logs", params={**query, "skill": "bulk"})
                timings[kind].append((time.perf_counter() - began) * 1000)
                if answer.status_code != 200:
                    raise RuntimeError(f"the query failed: {answer.status_code} {answer.text[:300]}")
                found = len(answer.json()["results"])
                if found != QUERY_LINES // 200_000:
                    raise RuntimeError(f"the {kind} query found {found} lines, not {QUERY_LINES // 200_000}")
    return {
        "query_1m_lines_ms": round(statistics.median(timings["substring"]), 1),
        "query_1m_regex_ms": round(statistics.median(timings["regex"]), 1),
    }


def cli_start_ms(quick: bool) -> float:
    """Return the median wall time of `bridgeos --help`, in milliseconds."""
    script = Path(sys.executable).parent / "bridgeos"
    timings = []
    for _ in range(5 if quick else 11):
        began = time.perf_counter()
        subprocess.run([str(script), "--help"], check=True, stdout=subprocess.DEVNULL)
        timings.append((time.perf_counter() - began) * 1000)
    return round(statistics.median(timings), 1)


async def main_async(bench: Cloud, tokens: dict[str, str], flag: Path, stop: Path, quick: bool) -> dict[str, Any]:
    figures = await agent_run(bench, tokens, flag, stop, quick)
    figures.update(await query_run(bench, tokens, quick))
    return figures


def main() -> None:
    parser = arguments(
        __doc__, "8 s windows and fewer query repeats: under a minute", database="bridgeos_bench_logs", redis=7
    )
    args = parser.parse_args()
    log(machine_load())
    figures: dict[str, Any] = {"cli_start_ms": cli_start_ms(args.quick)}
    with cloud(args, "bridgeos-bench-logs-", remove_data=True) as bench:
        from asgiref.sync import async_to_sync  # noqa: F401  (Django set up by now)

        flag, stop = bench.data_dir / "flood", bench.data_dir / "stop"
        tokens = setup_fleet(flag, stop)
        bench.start_daphne()
        figures.update(asyncio.run(main_async(bench, tokens, flag, stop, args.quick)))
    log(
        f"stored {figures['lines_per_s_stored']:,} lines/s under a flood; tail p95 {figures['tail_p95_ms']} ms; "
        f"metrics lag {figures['metrics_lag_quiet_ms']} ms quiet, {figures['metrics_lag_flood_ms']} ms flooded; "
        f"a text query over 1M lines {figures['query_1m_lines_ms']} ms; `bridgeos --help` {figures['cli_start_ms']} ms"
    )
    report(figures)


if __name__ == "__main__":
    main()
