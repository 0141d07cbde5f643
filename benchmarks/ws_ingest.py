"""Metric ingest at fleet scale: N robots on /ws/robot/, one dashboard on /ws/client/.

Each robot sends `--rate` points a second in frames of `--points-per-frame`; the benchmark
prints the sustained rate of rows committed to PostgreSQL, the lag from send to the robot's
ack (acks follow the commit, so this is the lag to the database) and to the dashboard,
connections dropped, and daphne's memory and CPU. Goal on our 2-core machine: >=10,000
points/s stored, p95 lag <=1 s, 0 drops at 1000 robots. The thesis measured one robot only.

    .venv/bin/python benchmarks/ws_ingest.py --quick
    .venv/bin/python benchmarks/ws_ingest.py --robots 1000 --duration 30
"""

from __future__ import annotations

import argparse
import asyncio
import gc
import json
import math
import multiprocessing as mp
import os
import random
import resource
import sys
import time
from array import array
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ROOT, Daphne, log, percentile
from _harness import Clients, arguments, cloud, create_fleet, forget_fleet, report, shares

ROBOT_PREFIX = "bench-"
OPERATOR = "bench-operator"
METRIC_NAMES = ["cpu", "ram", "disk", "net_rx", "net_tx", "gpu", "temp", "battery", "io_read", "io_write"]
# Cloud frames a robot must ack, or they are retransmitted.
NEEDS_ACK = {"connection_established", "robot_config"}
# Per-worker counters in shared memory: one writer each, read by the parent for progress.
CONNECTED, FAILED, CLOSED, SENT, ACKED, POINTS_ACKED, ERRORS, LATE = range(8)
N_COUNTERS = 8


# --------------------------------------------------------------------------- the robot fleet (worker processes)


class Robot:
    """One simulated robot: authenticate, ack what needs it, send metrics on a schedule."""

    def __init__(self, fleet: Fleet, robot_id: str, token: str) -> None:
        self.fleet = fleet
        self.robot_id = robot_id
        self.token = token
        self.ws = None
        self.pending: dict[str, float] = {}  # frame id -> wall time sent
        self.authenticated = asyncio.Event()
        self.seq = 0
        self.lost = False

    async def run(self) -> None:
        from websockets.asyncio.client import connect

        fleet = self.fleet
        counters = fleet.counters
        base = fleet.base
        try:
            async with fleet.gate:
                self.ws = await connect(
                    fleet.url + "/ws/robot/",
                    compression=None,
                    ping_interval=None,  # daphne pings; answering is automatic
                    max_size=2**21,
                    open_timeout=30,
                    close_timeout=5,
                )
                reader = asyncio.create_task(self.read())
                await self.ws.send(
                    json.dumps(
                        {
                            "event": "authentication_robot",
                            "id": "auth",
                            "reply_to": None,
                            "data": {"robot": self.robot_id, "token": self.token},
                            "ts": time.time(),
                        }
                    )
                )
                await asyncio.wait_for(self.authenticated.wait(), 30)
        except Exception as exc:
            counters[base + FAILED] += 1
            fleet.note(f"{self.robot_id}: connect/auth failed: {exc!r}")
            self.lost = True
            if self.ws is not None:
                try:
                    await self.ws.close()
                except Exception:
                    pass
            return
        counters[base + CONNECTED] += 1
        await self.send_loop(reader)

    async def send_loop(self, reader: asyncio.Task) -> None:
        fleet = self.fleet
        counters = fleet.counters
        base = fleet.base
        loop = asyncio.get_running_loop()
        period = fleet.period
        next_at = loop.time() + random.uniform(0, period)
        names = fleet.names
        head = '{"event":"metrics","id":"'
        try:
            while not fleet.stopping and not reader.done():
                delay = next_at - loop.time()
                if delay > 0:
                    await asyncio.sleep(delay)
                    if fleet.stopping or reader.done():
                        break
                late = loop.time() - next_at
                fleet.late.append(late)
                if late > period:
                    counters[base + LATE] += 1
                    next_at = loop.time()
                next_at += period
                self.seq += 1
                frame_id = f"m{self.seq}"
                now = time.time()
                points = ",".join(
                    f'{{"name":"{name}","value":{random.random() * 100:.3f},"ts":{now!r}}}' for name in names
                )
                self.pending[frame_id] = now
                await self.ws.send(f'{head}{frame_id}","reply_to":null,"data":{{"metrics":[{points}]}},"ts":{now!r}}}')
                counters[base + SENT] += 1
            # Give the cloud time to ack what is in flight; a frame never acked is a loss.
            deadline = loop.time() + fleet.grace
            while self.pending and not reader.done() and loop.time() < deadline:  # noqa: ASYNC110
                await asyncio.sleep(0.1)
        except Exception as exc:
            if not fleet.stopping:
                fleet.note(f"{self.robot_id}: send failed: {exc!r}")
        if reader.done() and not fleet.stopping:
            self.lost = True
        if self.pending:
            fleet.unacked += len(self.pending)
            fleet.robots_with_unacked.append(self.robot_id)

    async def read(self) -> None:
        fleet = self.fleet
        counters = fleet.counters
        base = fleet.base
        ppf = fleet.points_per_frame
        try:
            async for raw in self.ws:
                frame = json.loads(raw)
                event = frame.get("event")
                if event == "ack":
                    sent = self.pending.pop(frame.get("reply_to"), None)
                    if sent is not None:
                        fleet.db_lags.append(sent)
                        fleet.db_lags.append(time.time() - sent)
                        counters[base + ACKED] += 1
                        counters[base + POINTS_ACKED] += ppf
                elif event in NEEDS_ACK:
                    self.seq += 1
                    ack = {"event": "ack", "id": f"a{self.seq}", "reply_to": frame["id"], "data": {}, "ts": time.time()}
                    await self.ws.send(json.dumps(ack))
                elif event == "authentication_success":
                    self.authenticated.set()
                elif event in ("error_message", "authentication_failure"):
                    counters[base + ERRORS] += 1
                    fleet.note(f"{self.robot_id}: {event} {frame.get('data')}")
        except Exception as exc:
            if not fleet.stopping:
                fleet.note(f"{self.robot_id}: connection lost: {exc!r}")
        if not fleet.stopping:
            counters[base + CLOSED] += 1


class Fleet:
    """The robots of one worker process."""

    def __init__(self, url, robots, counters, base, stop_event, args) -> None:
        self.url = url
        self.robots = [Robot(self, robot_id, token) for robot_id, token in robots]
        self.counters = counters
        self.base = base
        self.stop_event = stop_event
        self.stopping = False
        self.period = args["points_per_frame"] / args["rate"]
        self.points_per_frame = args["points_per_frame"]
        self.names = [METRIC_NAMES[i] if i < len(METRIC_NAMES) else f"m{i}" for i in range(args["points_per_frame"])]
        self.grace = args["grace"]
        self.gate = asyncio.Semaphore(args["connect_concurrency"])
        self.db_lags = array("d")  # pairs: wall time sent, seconds to ack
        self.late = array("d")
        self.unacked = 0
        self.robots_with_unacked: list[str] = []
        self.notes: list[str] = []

    def note(self, message: str) -> None:
        if len(self.notes) < 20:
            self.notes.append(message)

    async def run(self) -> dict:
        tasks = [asyncio.create_task(robot.run()) for robot in self.robots]
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(None, self.stop_event.wait)
        self.stopping = True
        await asyncio.gather(*tasks, return_exceptions=True)
        result = {
            "db_lags": self.db_lags.tobytes(),
            "late_p95_ms": (percentile(list(self.late[-20000:]), 95) or 0.0) * 1000,
            "unacked": self.unacked,
            "robots_with_unacked": self.robots_with_unacked,
            "lost": [robot.robot_id for robot in self.robots if robot.lost],
            "notes": self.notes,
            "cpu_s": sum(resource.getrusage(resource.RUSAGE_SELF)[:2]),
        }
        await asyncio.gather(*(r.ws.close() for r in self.robots if r.ws is not None), return_exceptions=True)
        return result


def fleet_main(index, robots, start_event, stop_event, result_queue, url, counters, args) -> None:
    """Entry point of a worker process: run its robots until told to stop, then report."""
    # The fork inherits the parent's objects; without this, the worker's own full collections
    # would pause its robots and be counted as lag.
    gc.freeze()
    start_event.wait()
    try:
        result = asyncio.run(Fleet(url, robots, counters, index * N_COUNTERS, stop_event, args).run())
    except BaseException as exc:
        result = {"crash": repr(exc)}
    result_queue.put(result)


# --------------------------------------------------------------------------- setup


def prepare(args: argparse.Namespace) -> tuple[list[tuple[str, str]], str]:
    """Delete earlier bench robots and create N fresh ones; return their tokens and an API token."""
    from django.contrib.auth import get_user_model
    from django.db import connection

    from monitoring.models import Metric
    from robots.services import issue_api_token

    started = time.monotonic()
    forget_fleet(ROBOT_PREFIX, metrics=True)
    with connection.cursor() as cursor:
        # Reclaim the deleted rows now: an autovacuum during the measurement would slow every COPY.
        cursor.execute(f"VACUUM ANALYZE {Metric._meta.db_table}")
    user, _ = get_user_model().objects.get_or_create(username=OPERATOR, defaults={"is_staff": True})
    if not user.is_staff:
        user.is_staff = True
        user.save(update_fields=["is_staff"])
    api_token, _ = issue_api_token(user)
    tokens = create_fleet(user, args.robots, ROBOT_PREFIX, digits=5, batch_size=1000)
    connection.close()
    log(f"created {args.robots} robots in {time.monotonic() - started:.1f} s")
    return tokens, api_token


# --------------------------------------------------------------------------- the dashboard and the measurement


class Dashboard:
    """One staff client on /ws/client/: record the lag of every live metrics frame."""

    def __init__(self, url: str, token: str) -> None:
        self.url = url
        self.token = token
        self.lags = array("d")  # pairs: wall time received, seconds since the newest point
        self.frames = 0
        self.dropped = False
        self.stopping = False

    async def connect(self) -> None:
        from websockets.asyncio.client import connect

        self.ws = await connect(self.url + "/ws/client/", compression=None, ping_interval=None, max_size=2**23)
        auth = {"event": "authentication_client", "id": "auth", "reply_to": None, "data": {"token": self.token}}
        await self.ws.send(json.dumps({**auth, "ts": time.time()}))
        while True:
            frame = json.loads(await asyncio.wait_for(self.ws.recv(), 30))
            if frame["event"] == "authentication_success":
                break
            if frame["event"] == "authentication_failure":
                raise RuntimeError(f"dashboard refused: {frame['data']}")
        self.task = asyncio.create_task(self.read())

    async def read(self) -> None:
        lags = self.lags
        try:
            async for raw in self.ws:
                now = time.time()
                # Cheap pre-check: only metrics frames matter, and they are most of the traffic.
                if raw.startswith('{"event":"metrics"'):
                    frame = json.loads(raw)
                    newest = max(point["ts"] for point in frame["data"]["metrics"])
                    lags.append(now)
                    lags.append(now - newest)
                    self.frames += 1
        except Exception as exc:
            log(f"dashboard connection failed: {exc!r}")
        if not self.stopping:
            self.dropped = True

    async def close(self) -> None:
        self.stopping = True
        await self.ws.close()


def window_lags(pairs: array, t0: float, t1: float) -> list[float]:
    """Return the lags (ms) whose time stamp falls in the measured window."""
    return [pairs[i + 1] * 1000 for i in range(0, len(pairs), 2) if t0 <= pairs[i] <= t1]


async def count_rows(conn) -> tuple[int, float]:
    """Count the bench robots' committed metric rows; return the count and when it was taken."""
    before = time.time()
    cursor = await conn.execute("SELECT count(*) FROM monitoring_metric WHERE robot_id LIKE %s", [ROBOT_PREFIX + "%"])
    (count,) = await cursor.fetchone()
    return count, (before + time.time()) / 2


def _ms(value: float | None) -> float | None:
    """Round a lag; None (JSON null) when nothing was received, never a flattering 0."""
    return None if value is None else round(value, 1)


def fmt(value: float | None, digits: int = 0) -> str:
    return "n/a" if value is None else f"{value:,.{digits}f}"


class Workers(Clients):
    """The robot client processes, counting in shared memory; they start on a signal."""

    def __init__(self, args: argparse.Namespace, url: str, tokens: list[tuple[str, str]]) -> None:
        self.count = args.procs or max(1, math.ceil(args.robots / 500))
        self.counters = mp.get_context("fork").Array("q", N_COUNTERS * self.count, lock=False)
        worker_args = {
            "rate": args.rate,
            "points_per_frame": args.points_per_frame,
            "grace": args.grace,
            "connect_concurrency": max(1, args.connect_concurrency // self.count),
        }
        super().__init__(fleet_main, shares(tokens, self.count), url, self.counters, worker_args)

    def total(self, index: int) -> int:
        return sum(self.counters[p * N_COUNTERS + index] for p in range(self.count))


async def measure(args, daphne: Daphne, workers: Workers, api_token, database_url: str) -> dict:
    import psycopg

    procs = workers.count
    total = workers.total
    dashboard = Dashboard(daphne.ws_url, api_token)
    await dashboard.connect()
    conn = await psycopg.AsyncConnection.connect(database_url, autocommit=True)

    started = time.monotonic()
    workers.start_event.set()
    log(f"ramp-up: {args.robots} robots in {procs} process(es), {args.connect_concurrency} connecting at a time")
    while total(CONNECTED) + total(FAILED) < args.robots:
        await asyncio.sleep(1)
        log(f"ramp-up: {total(CONNECTED)}/{args.robots} connected, {total(FAILED)} failed")
        if time.monotonic() - started > args.ramp_timeout:
            log("ramp-up timed out; measuring the robots that made it")
            break
    ramp_s = time.monotonic() - started
    await asyncio.sleep(args.warmup)

    count0, t0 = await count_rows(conn)
    cpu0, sent0 = daphne.cpu_seconds(), total(SENT)
    acked_last, last = total(POINTS_ACKED), time.time()
    log(f"measuring {args.duration:g} s (ramp-up took {ramp_s:.1f} s)")
    end = t0 + args.duration
    while time.time() < end:
        await asyncio.sleep(min(5.0, max(0.0, end - time.time())))
        now, acked = time.time(), total(POINTS_ACKED)
        recent = window_lags(dashboard.lags, now - 5, now)
        log(
            f"{now - t0:5.1f} s: {(acked - acked_last) / (now - last):,.0f} points/s stored (acked), "
            f"client lag p95 {fmt(percentile(recent, 95))} ms, "
            f"connected {total(CONNECTED) - total(CLOSED)}, "
            f"daphne CPU {100 * (daphne.cpu_seconds() - cpu0) / (now - t0):.0f}%"
        )
        acked_last, last = acked, now
    count1, t1 = await count_rows(conn)
    cpu1, sent1 = daphne.cpu_seconds(), total(SENT)
    rss, peak = daphne.memory_mib()
    late_frames = total(LATE)

    workers.stop_event.set()
    reports = await asyncio.get_running_loop().run_in_executor(None, workers.reports, args.grace + 60)
    await dashboard.close()
    # Every frame has been acked (or counted lost) by now, so the points sent inside the window
    # that reached the database give the sustained rate without the window-edge noise of
    # counting rows at two instants a flush apart.
    cursor = await conn.execute(
        "SELECT count(*) FROM monitoring_metric"
        " WHERE robot_id LIKE %s AND ts >= to_timestamp(%s) AND ts < to_timestamp(%s)",
        [ROBOT_PREFIX + "%", t0, t1],
    )
    (stored_in_window,) = await cursor.fetchone()
    await conn.close()
    crashed = [r["crash"] for r in reports if "crash" in r]
    if crashed:
        raise RuntimeError(f"a robot worker crashed: {crashed}")

    db_pairs = array("d")
    for each in reports:
        db_pairs.frombytes(each["db_lags"])
    db_lags = window_lags(db_pairs, t0, t1)
    client_lags = window_lags(dashboard.lags, t0, t1)
    lost = sorted(robot for report in reports for robot in report["lost"])
    failed_connects = total(FAILED)
    closed = total(CLOSED)
    with_unacked = [robot for report in reports for robot in report["robots_with_unacked"]]
    notes = [note for report in reports for note in report["notes"]][:10]
    for note in notes:
        log(f"note: {note}")
    elapsed = t1 - t0
    return {
        "points_per_s": round(stored_in_window / elapsed, 1),
        "committed_points_per_s": round((count1 - count0) / elapsed, 1),
        "offered_points_per_s": round(total(CONNECTED) * args.rate, 1),
        "sent_points_per_s": round((sent1 - sent0) * args.points_per_frame / elapsed, 1),
        "lag_p50_ms": _ms(percentile(client_lags, 50)),
        "lag_p95_ms": _ms(percentile(client_lags, 95)),
        "db_lag_p50_ms": _ms(percentile(db_lags, 50)),
        "db_lag_p95_ms": _ms(percentile(db_lags, 95)),
        "dropped_connections": len(set(lost) | set(with_unacked)),
        "failed_connects": failed_connects,
        "closed_unexpectedly": closed,
        "unacked_frames": sum(r["unacked"] for r in reports),
        "error_frames": total(ERRORS),
        "dashboard_dropped": dashboard.dropped,
        "dashboard_frames_per_s": round(len(client_lags) / elapsed, 1),
        "robots": args.robots,
        "robots_connected": total(CONNECTED),
        "robot_processes": procs,
        "ramp_up_s": round(ramp_s, 1),
        "duration_s": round(elapsed, 1),
        "daphne_rss_mib": round(rss, 1),
        "daphne_peak_rss_mib": round(peak, 1),
        "daphne_cpu_percent": round(100 * (cpu1 - cpu0) / elapsed, 1),
        "client_send_late_p95_ms": round(max(r["late_p95_ms"] for r in reports), 1),
        "client_late_frames": late_frames,
        "client_cpu_s": round(sum(r["cpu_s"] for r in reports), 1),
    }


def summary(result: dict) -> None:
    r = result
    lines = [
        f"robots: {r['robots']} ({r['robots_connected']} connected, {r['robot_processes']} client process(es), "
        f"ramp-up {r['ramp_up_s']} s), measured {r['duration_s']} s",
        f"points/s offered: {r['offered_points_per_s']:,.0f} (sent {r['sent_points_per_s']:,.0f})",
        f"points/s stored: {r['points_per_s']:,.0f} of those sent in the window "
        f"(committed during it: {r['committed_points_per_s']:,.0f}) (goal >=10,000 at 1000 robots; "
        "thesis: one robot, no figure for a fleet)",
        f"lag to dashboard p50/p95: {fmt(r['lag_p50_ms'])} / {fmt(r['lag_p95_ms'])} ms "
        "(goal p95 <=1,000 ms; includes the live feed's 250 ms coalescing tick; thesis: one robot)",
        f"lag to database (ack after commit) p50/p95: {fmt(r['db_lag_p50_ms'])} / {fmt(r['db_lag_p95_ms'])} ms",
        f"dropped connections: {r['dropped_connections']} (goal 0; failed to connect {r['failed_connects']}, "
        f"closed {r['closed_unexpectedly']}, frames never acked {r['unacked_frames']}, "
        f"error frames {r['error_frames']}, dashboard dropped {r['dashboard_dropped']})",
        f"dashboard frames/s: {r['dashboard_frames_per_s']:,.0f}",
        f"daphne: RSS {r['daphne_rss_mib']:.0f} MiB (peak {r['daphne_peak_rss_mib']:.0f}), "
        f"CPU {r['daphne_cpu_percent']:.0f}% of one core",
        f"benchmark client: send lateness p95 {r['client_send_late_p95_ms']:.0f} ms, "
        f"{r['client_late_frames']} frames over a period late, {r['client_cpu_s']} CPU s",
    ]
    print("\n".join(lines), flush=True)


def main() -> None:
    parser = arguments(__doc__, "200 robots for 15 s: under a minute in all", database="bridgeos_bench", redis=12)
    parser.add_argument("--robots", type=int, default=500)
    parser.add_argument("--duration", type=float, default=60.0, help="measured seconds after ramp-up")
    parser.add_argument("--rate", type=float, default=10.0, help="points per robot per second")
    parser.add_argument("--points-per-frame", type=int, default=10)
    parser.add_argument("--procs", type=int, default=0, help="robot client processes (0: one per 500 robots)")
    parser.add_argument("--connect-concurrency", type=int, default=50)
    parser.add_argument("--warmup", type=float, default=3.0)
    parser.add_argument("--grace", type=float, default=10.0, help="seconds to wait for outstanding acks")
    parser.add_argument("--ramp-timeout", type=float, default=120.0)
    args = parser.parse_args()
    if args.quick:
        args.robots, args.duration, args.warmup = min(args.robots, 200), min(args.duration, 15.0), 2.0
    if args.robots < 1 or args.rate <= 0 or args.points_per_frame < 1 or args.duration <= 0:
        parser.error("robots, rate, points per frame and duration must be positive")

    with cloud(args, "bridgeos-bench-") as bench:
        tokens, api_token = prepare(args)
        daphne = bench.start_daphne()
        log(f"daphne pid {daphne.pid} on port {daphne.port}")
        workers = Workers(args, daphne.ws_url, tokens)
        try:
            result = asyncio.run(measure(args, daphne, workers, api_token, args.database_url))
        finally:
            workers.kill()
    summary(result)
    report(result)


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
