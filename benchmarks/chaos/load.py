"""Scenario 8, load: many robots stream metrics at 10 points/s while an operator issues commands through REST.

Simulated robots speak the real robot protocol on /ws/robot/ from a few worker processes (like
benchmarks/connect_storm.py): they authenticate, ack what the cloud sends, send a metrics frame
of 10 points every second (as the agent sends each second's samples) and ack each command relayed
to them. Meanwhile an operator calls `POST /api/robot/<id>/start` on random robots; each call must
round-trip to the robot and back.
Figures: command p99 (the REST call's time), ingest p95 (a point's send to its ack, which the
cloud sends once its row is committed), and points lost and duplicated, counted in PostgreSQL.
"""

from __future__ import annotations

import asyncio
import json
import logging
import multiprocessing as mp
import random
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

from benchmarks._common import log, percentile
from benchmarks.chaos import Outcome
from benchmarks.chaos.rig import shared_cloud_env, start_daphne

NAME = "load"
ROBOT_PREFIX = "load-"
OPERATOR = "load-operator"
# One frame of 10 points a second, as the agent sends what it sampled each second (sample_interval 1 s).
POINTS_PER_FRAME = 10
FRAME_PERIOD_S = 1.0
# (robots, seconds streaming, commands per second) of each form.
FULL = (1000, 60.0, 10.0)
QUICK = (200, 15.0, 10.0)
INJECTS = (
    f"load: {FULL[0]} robots x 10 points/s for {FULL[1]:g} s with REST commands "
    f"(quick: {QUICK[0]} robots for {QUICK[1]:g} s)"
)
PROCS = 3
ACK_GRACE_S = 15.0


# --------------------------------------------------------------------------- the fleet (worker processes)


@dataclass
class FleetReport:
    """What one worker's robots did."""

    connected: int = 0
    failed: list[str] = field(default_factory=list)
    frames: int = 0
    points: int = 0
    unacked: int = 0
    refused: int = 0
    ingest_ms: list[float] = field(default_factory=list)  # one per acked frame (its points share it)
    commands: int = 0
    command_duplicates: int = 0


async def one_robot(
    url: str,
    robot_id: str,
    token: str,
    gate: asyncio.Semaphore,
    go: asyncio.Event,
    stop_at: list[float],
    leave: asyncio.Event,
    report: FleetReport,
) -> None:
    """Connect one robot, stream metrics until ``stop_at[0]``, ack every command once, wait for its acks."""
    from websockets.asyncio.client import connect

    from bridgeos_agent import protocol

    pending: dict[str, float] = {}
    commands_seen: set[str] = set()
    authenticated = asyncio.Event()

    async def read(ws: Any) -> None:
        async for raw in ws:
            frame = json.loads(raw)
            event = frame["event"]
            if event == "authentication_success":
                authenticated.set()
            elif event == "authentication_failure":
                raise RuntimeError(f"refused: {frame['data']}")
            elif event == "ack":
                sent = pending.pop(frame.get("reply_to"), None)
                if sent is not None:
                    report.ingest_ms.append((time.time() - sent) * 1000)
            elif event == "error_message" and frame.get("reply_to") in pending:
                pending.pop(frame["reply_to"])
                report.refused += 1
            if event in protocol.REQUIRES_ACK:
                if event in protocol.COMMANDS:
                    if frame["id"] in commands_seen:
                        report.command_duplicates += 1  # a retransmission: acked again, applied once
                    else:
                        commands_seen.add(frame["id"])
                        report.commands += 1
                await ws.send(protocol.ack_text(frame["id"], now=time.time()))

    try:
        async with gate:
            ws = await connect(url, compression=None, ping_interval=None, open_timeout=60, max_size=2**22)
            reader = asyncio.create_task(read(ws))
            auth = {"event": "authentication_robot", "id": "auth", "data": {"robot": robot_id, "token": token}}
            await ws.send(json.dumps(auth))
            await asyncio.wait_for(asyncio.shield(authenticated.wait()), 60)
    except Exception as exc:
        report.failed.append(f"{robot_id}: {exc!r}")
        return
    report.connected += 1
    await go.wait()
    loop = asyncio.get_running_loop()
    next_at = loop.time() + random.uniform(0, FRAME_PERIOD_S)
    seq = 0
    run_tag = f"{random.getrandbits(48):012x}"
    try:
        while time.time() < stop_at[0] and not reader.done():
            await asyncio.sleep(max(0.0, next_at - loop.time()))
            next_at += FRAME_PERIOD_S
            seq += 1
            now = time.time()
            # Unique across runs, as an agent's ids are: the cloud remembers applied ids per robot id.
            frame_id = f"{run_tag}-{seq}"
            # Each point is unique by (robot, name, ts): the database tells lost from duplicated.
            points = ",".join(f'{{"name":"load.p{k}","value":{seq}.{k},"ts":{now!r}}}' for k in range(POINTS_PER_FRAME))
            pending[frame_id] = now
            await ws.send(f'{{"event":"metrics","id":"{frame_id}","reply_to":null,"data":{{"metrics":[{points}]}}}}')
            report.frames += 1
            report.points += POINTS_PER_FRAME
        deadline = loop.time() + ACK_GRACE_S
        while pending and not reader.done() and loop.time() < deadline:  # noqa: ASYNC110 - acks arrive on the reader
            await asyncio.sleep(0.1)
    except Exception as exc:
        report.failed.append(f"{robot_id}: stream broke: {exc!r}")
    if reader.done() and reader.exception() is not None:
        report.failed.append(f"{robot_id}: connection lost: {reader.exception()!r}")
    report.unacked += len(pending)
    # Connected, still answering commands, until the operator's last call came back.
    if not reader.done():
        await leave.wait()
    reader.cancel()
    await ws.close()


def fleet_worker(
    url: str, robots: list[tuple[str, str]], ready: Any, start: Any, finish: Any, seconds: float, queue: Any
) -> None:
    """Run a share of the robots in a process of its own: stream ``seconds`` from ``start``, leave on ``finish``."""

    async def main() -> FleetReport:
        report = FleetReport()
        gate = asyncio.Semaphore(50)  # connect in waves, as a fleet coming online would
        go, leave = asyncio.Event(), asyncio.Event()
        stop_at = [float("inf")]
        tasks = [asyncio.create_task(one_robot(url, rid, tok, gate, go, stop_at, leave, report)) for rid, tok in robots]
        while report.connected + len(report.failed) < len(robots):  # noqa: ASYNC110
            await asyncio.sleep(0.05)
        ready.set()
        await asyncio.to_thread(start.wait)
        stop_at[0] = time.time() + seconds
        go.set()
        await asyncio.to_thread(finish.wait)
        leave.set()
        await asyncio.gather(*tasks)
        return report

    queue.put(asyncio.run(main()))


# --------------------------------------------------------------------------- the operator (this process)


@dataclass
class Operator:
    """Calls REST commands on random robots at a steady rate and times each round trip."""

    http: str
    token: str
    robot_ids: list[str]
    rate: float
    times_ms: list[float] = field(default_factory=list)
    failures: list[str] = field(default_factory=list)
    sent: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)

    def call(self, client: Any, robot_id: str) -> None:
        started = time.monotonic()
        try:
            response = client.post(f"/api/robot/{robot_id}/start", params={"wait": 30})
            took = (time.monotonic() - started) * 1000
            ok = response.status_code == 200 and response.json().get("accepted") is True
            with self.lock:
                self.times_ms.append(took)
                if not ok:
                    self.failures.append(f"{robot_id}: {response.status_code} {response.text[:150]}")
        except Exception as exc:
            with self.lock:
                self.failures.append(f"{robot_id}: {exc!r}")

    def run(self, until: float) -> None:
        import httpx

        rng = random.Random(8)
        headers = {"Authorization": f"Token {self.token}"}
        with httpx.Client(base_url=self.http, headers=headers, timeout=60) as client, ThreadPoolExecutor(16) as pool:
            next_at = time.monotonic()
            while time.time() < until:
                time.sleep(max(0.0, next_at - time.monotonic()))
                next_at += 1 / self.rate
                pool.submit(self.call, client, rng.choice(self.robot_ids))
                self.sent += 1


# --------------------------------------------------------------------------- setup and counting


def prepare(robots: int) -> tuple[list[tuple[str, str]], str]:
    """Create the scenario's robots afresh, each with its own token; return them and the operator's API token."""
    from django.contrib.auth import get_user_model
    from django.db import connection

    from monitoring.models import Metric
    from robots.models import Robot, default_robot_config
    from robots.services import issue_api_token
    from teams.services import personal_organization

    with connection.cursor() as cursor:
        # Straight SQL: a cascade through the ORM would walk every old metric row.
        cursor.execute(f"DELETE FROM {Metric._meta.db_table} WHERE robot_id LIKE %s", [ROBOT_PREFIX + "%"])
    Robot.objects.filter(id__startswith=ROBOT_PREFIX).delete()
    operator, _ = get_user_model().objects.get_or_create(username=OPERATOR)
    config = default_robot_config()
    rows, tokens = [], []
    for i in range(robots):
        robot = Robot(
            id=f"{ROBOT_PREFIX}{i:05d}", owner=operator, organization=personal_organization(operator), config=config
        )
        tokens.append((robot.id, robot.issue_token()))
        rows.append(robot)
    Robot.objects.bulk_create(rows, batch_size=1000)
    api_token = issue_api_token(operator)[0]
    connection.close()
    return tokens, api_token


def stored_points() -> tuple[int, int]:
    """Return (rows, distinct points) the scenario's robots have in PostgreSQL."""
    from django.db import connection

    from monitoring.models import Metric

    with connection.cursor() as cursor:
        cursor.execute(
            f"SELECT count(*), count(DISTINCT (robot_id, name, ts)) FROM {Metric._meta.db_table}"
            " WHERE robot_id LIKE %s AND name LIKE 'load.p%%'",
            [ROBOT_PREFIX + "%"],
        )
        rows, distinct = cursor.fetchone()
    connection.close()
    return rows, distinct


# --------------------------------------------------------------------------- the scenario


def play(robots: int, seconds: float, command_rate: float) -> Outcome:
    """Stream from ``robots`` robots for ``seconds`` while commands go out at ``command_rate`` per second."""
    env = shared_cloud_env()
    tokens, api_token = prepare(robots)
    daphne = start_daphne(env, NAME)
    ctx = mp.get_context("spawn")
    queue: mp.Queue = ctx.Queue()
    procs = min(PROCS, robots)
    readies = [ctx.Event() for _ in range(procs)]
    start, finish = ctx.Event(), ctx.Event()
    started = time.monotonic()
    workers = []
    try:
        url = daphne.ws_url + "/ws/robot/"
        shares = [tokens[i::procs] for i in range(procs)]
        # Every worker streams for ``seconds`` from the moment ``start`` is set.
        workers = [
            ctx.Process(target=fleet_worker, args=(url, share, ready, start, finish, seconds, queue))
            for share, ready in zip(shares, readies, strict=True)
        ]
        for worker in workers:
            worker.start()
        for ready in readies:
            if not ready.wait(180):
                raise TimeoutError("the fleet did not connect within 180 s")
        connect_s = time.monotonic() - started
        log(f"  {robots} robots connected in {connect_s:.1f} s; streaming for {seconds:g} s")
        start.set()
        until = time.time() + seconds
        operator = Operator(f"http://127.0.0.1:{daphne.port}", api_token, [rid for rid, _ in tokens], command_rate)
        operator.run(until)  # returns once every call it made came back
        finish.set()
        reports: list[FleetReport] = [queue.get(timeout=seconds + ACK_GRACE_S + 120) for _ in workers]
        for worker in workers:
            worker.join(timeout=30)
    except BaseException:
        log(f"daphne log tail:\n{daphne.log_tail()}")
        raise
    finally:
        for worker in workers:
            if worker.is_alive():
                worker.kill()
        daphne.stop()
    rows, distinct = stored_points()
    points = sum(r.points for r in reports)
    ingest = [ms for r in reports for ms in r.ingest_ms]
    failed = [f for r in reports for f in r.failed]
    lost = max(0, points - distinct)
    duplicated = rows - distinct
    commands_received = sum(r.commands for r in reports)
    command_p99 = percentile(operator.times_ms, 99)
    ingest_p95 = percentile(ingest, 95)
    connected = sum(r.connected for r in reports)
    passed = (
        lost == 0
        and duplicated == 0
        and not operator.failures
        and not failed
        and connected == robots
        and operator.sent > 0
        and commands_received == operator.sent
    )
    detail = (
        f"{connected}/{robots} robots connected in {connect_s:.1f} s; {sum(r.frames for r in reports)} frames, "
        f"{points} points sent ({points / seconds:.0f}/s), {distinct} stored, {rows} rows; "
        f"{sum(r.unacked for r in reports)} frames unacked, {sum(r.refused for r in reports)} refused; "
        f"{operator.sent} commands, {commands_received} reached robots once "
        f"({sum(r.command_duplicates for r in reports)} retransmissions), {len(operator.failures)} failed; "
        f"command p50 {percentile(operator.times_ms, 50) or 0:.0f} ms p99 {command_p99 or 0:.0f} ms; "
        f"ingest p50 {percentile(ingest, 50) or 0:.0f} ms p95 {ingest_p95 or 0:.0f} ms"
        + (f"; failures: {operator.failures[:3]}" if operator.failures else "")
        + (f"; robots failed: {failed[:3]} ({len(failed)})" if failed else "")
    )
    log(f"  {detail}")
    if not passed:
        notes = [line for line in daphne.log_tail(10**9).splitlines() if "WARNING" in line or "ERROR" in line]
        log("  daphne's warnings and errors:\n" + "\n".join(notes[:30]))
    return Outcome(
        scenario=NAME,
        injected=f"{robots} robots x 10 points/s for {seconds:g} s, {command_rate:g} REST commands/s",
        sent=points,
        stored=distinct,
        lost=lost,
        duplicated=duplicated,
        passed=passed,
        detail=detail,
        figures={
            "command_p99_ms": round(command_p99, 1) if command_p99 is not None else None,
            "ingest_p95_ms": round(ingest_p95, 1) if ingest_p95 is not None else None,
            "robots": robots,
            "commands": operator.sent,
            "commands_failed": len(operator.failures),
        },
    )


def run(quick: bool) -> list[Outcome]:
    """Play the load once: the quick form with fewer robots and a shorter stream."""
    logging.getLogger("httpx").setLevel(logging.WARNING)  # a line per request would drown the table
    robots, seconds, rate = QUICK if quick else FULL
    return [play(robots, seconds, rate)]
