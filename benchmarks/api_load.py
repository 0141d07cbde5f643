"""Robot API under load: 100 robots x 5 skills x 5 components, 50 concurrent REST clients.

Prints p50/p99 of GET /api/robot (the whole fleet) and of the /info routes (robot, skill,
component) under `--clients` concurrent clients, each reading `--client-rate` times a second
(open loop, latency counted from when a request was due; `--client-rate 0` sends back to
back instead, to find the saturation point); the round trip of a command (POST .../skill/<sid>/start) to a
connected robot until the HTTP answer carries the robot's ack, idle and under the load;
and the number of SQL queries GET /api/robot makes at 10 and at 100 robots. Goal: p99
<=50 ms for reads, a query count constant in fleet size. The routes are thesis Table 3.1;
the thesis gives no latency figure for the Robot API.

    .venv/bin/python benchmarks/api_load.py --quick
    .venv/bin/python benchmarks/api_load.py --duration 20
    .venv/bin/python benchmarks/api_load.py --quick --profile /tmp/api_load.txt   # py-spy on daphne
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import os
import random
import sys
import time
from array import array
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _api_load_profile import spawn_profiler, summarise_profile
from _api_load_reads import FAMILIES, INFO_FAMILIES, load_main, pick_path
from _common import ROOT, Daphne, log, percentile
from _harness import Clients, arguments, cloud, create_fleet, report

PREFIX = "api-bench-"
OPERATOR = "api-bench-operator"
SMALL_OWNER = "api-bench-small"
PASSWORD = "api-bench-pass-123"
SKILLS = 5
COMPONENTS = 5
SMALL_FLEET = 10
READ_GOAL_P99_MS = 50.0
COMMAND_PERIOD_S = 0.5


# --------------------------------------------------------------------------- setup (in-process, Django ORM)


def skill_configs() -> list[dict]:
    """Five distinct valid Skill configs of five components each, normalised by the schema."""
    from bridgeos_agent.skillconfig import parse_skill_config
    from bridgeos_cloud.validation import validated_config

    configs = []
    for k in range(SKILLS):
        components = {}
        for j in range(COMPONENTS):
            spec = {"command": ["sleep", "1"], "env": {"BENCH_SKILL": str(k)}}
            either = j % 2 == 1
            components[f"comp-{j}"] = {
                "name": f"Component {k}.{j}",
                "location": "either" if either else "robot",
                "resources": {"cpu": 0.1 * (j + 1), "ram": 64 * (k + 1)},
                "robot": spec,
                **({"cloud": spec} if either else {}),
            }
        raw = {"skill": f"Bench skill {k}", "skill_id": f"skill-{k}", "components": components}
        configs.append(validated_config(parse_skill_config, raw))
    return configs


def prepare(args: argparse.Namespace) -> dict:
    """Replace earlier bench data with a user owning the fleet, and one owning a small fleet."""
    from django.contrib.auth import get_user_model
    from django.db import connection

    from robots.models import Robot

    started = time.monotonic()
    Robot.objects.filter(id__startswith=PREFIX).delete()
    User = get_user_model()
    User.objects.filter(username__in=[OPERATOR, SMALL_OWNER]).delete()
    owner = User.objects.create_user(OPERATOR, password=PASSWORD)
    small = User.objects.create_user(SMALL_OWNER, password=PASSWORD)
    configs = skill_configs()
    tokens = create_fleet(owner, args.robots, PREFIX, named=True, skills=configs)
    create_fleet(small, SMALL_FLEET, PREFIX + "small-", named=True, skills=configs)
    # Earlier runs left dead rows behind; measure a database as autovacuum would keep it.
    with connection.cursor() as cursor:
        for table in ("auth_user", "robots_robot", "robots_apitoken", "skills_skill", "skills_component"):
            cursor.execute(f"VACUUM ANALYZE {table}")
    connection.close()
    log(
        f"created {args.robots} + {SMALL_FLEET} robots x {SKILLS} skills x {COMPONENTS} components "
        f"in {time.monotonic() - started:.1f} s"
    )
    return {
        "robots": [robot_id for robot_id, _ in tokens],
        "skills": [c["skill_id"] for c in configs],
        "components": list(configs[0]["components"]),
        "connected": tokens[0],
    }


def count_queries(fleet: dict) -> dict:
    """Count the SQL queries of each read route, in-process, at the small and the full fleet."""
    from django.contrib.auth import get_user_model
    from django.db import connection
    from django.test import Client
    from django.test.utils import CaptureQueriesContext

    from robots.services import issue_api_token

    User = get_user_model()

    def queries(username: str, path: str, expect: int | None = None) -> int:
        key, _ = issue_api_token(User.objects.get(username=username))
        client = Client(SERVER_NAME="localhost", HTTP_AUTHORIZATION=f"Token {key}")
        with CaptureQueriesContext(connection) as captured:
            response = client.get(path)
        if response.status_code != 200:
            raise RuntimeError(f"GET {path} answered {response.status_code}: {response.content[:300]!r}")
        if expect is not None and len(response.json()) != expect:
            raise RuntimeError(f"GET {path} listed {len(response.json())} robots, expected {expect}")
        return len(captured)

    robot, skill, component = fleet["robots"][-1], fleet["skills"][-1], fleet["components"][-1]
    result = {
        "list_small": queries(SMALL_OWNER, "/api/robot", SMALL_FLEET),
        "list_full": queries(OPERATOR, "/api/robot", len(fleet["robots"])),
        "robot_info": queries(OPERATOR, f"/api/robot/{robot}/info"),
        "skill_info": queries(OPERATOR, f"/api/robot/{robot}/skill/{skill}/info"),
        "component_info": queries(OPERATOR, f"/api/robot/{robot}/skill/{skill}/component/{component}/info"),
    }
    connection.close()
    return result


# --------------------------------------------------------------------------- commands and the measurement


async def command_round_trips(
    http, path: str, count: int | None, until: float | None = None, *, strict: bool = True
) -> list[tuple]:
    """POST a command again and again; return (wall time sent, seconds to the robot's ack) pairs.

    A command that fails raises when strict, else its seconds are None.
    """
    out = []
    while (count is None or len(out) < count) and (until is None or time.time() < until):
        sent = time.time()
        began = time.perf_counter()
        response = await http.post(path)
        elapsed = time.perf_counter() - began
        body = response.json() if response.status_code == 200 else {}
        if response.status_code != 200 or not body.get("accepted") or body["reply"]["event"] != "ack":
            if strict:
                raise RuntimeError(f"POST {path} answered {response.status_code}: {response.text[:300]}")
            log(f"command failed under load after {elapsed:.1f} s: {response.status_code} {response.text[:200]}")
            elapsed = None
        out.append((sent, elapsed))
    return out


async def measure(args, daphnes: list[Daphne], fleet: dict, token: str, loader: Clients) -> dict:
    # The robot is on the first process; commands enter through the last (another one when there are two).
    daphne = daphnes[0]
    import httpx

    from bridgeos_agent.link import Link
    from bridgeos_agent.protocol import Event

    robot_id, robot_token = fleet["connected"]
    link = Link(daphne.ws_url + "/ws/robot/")
    await link.connect(Event.AUTHENTICATION_ROBOT, {"robot": robot_id, "token": robot_token})
    await link.next(Event.CONNECTION_ESTABLISHED)
    await link.next(Event.ROBOT_CONFIG)
    log(f"robot {robot_id} connected")
    command = f"/api/robot/{robot_id}/skill/{fleet['skills'][0]}/start?wait=30"
    headers = {"Authorization": f"Token {token}"}
    loop = asyncio.get_running_loop()
    async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{daphnes[-1].port}", headers=headers, timeout=60) as http:
        # Warm daphne up: imports, database connections, the thread pool.
        for _ in range(3):
            for path in ("/api/robot", f"/api/robot/{robot_id}/info"):
                (await http.get(path)).raise_for_status()
        await command_round_trips(http, command, 5)
        # One client alone: each route's own cost, before any queueing.
        alone: dict[str, list[float]] = {}
        rnd = random.Random(0)
        for family in FAMILIES:
            share = 1.0 if family == "list" else 0.0
            for _ in range(args.alone if family != "list" else max(3, args.alone // 4)):
                while True:
                    index, path = pick_path(rnd, fleet, share)
                    if FAMILIES[index] == family:
                        break
                began = time.perf_counter()
                (await http.get(path)).raise_for_status()
                alone.setdefault(family, []).append(1000 * (time.perf_counter() - began))
        idle = [lag for _, lag in await command_round_trips(http, command, args.commands)]
        log(f"{len(idle)} idle command round trips: p50 {1000 * percentile(idle, 50):.1f} ms")

        log(f"read load: {args.clients} clients, {args.duration:g} s (+{args.warmup:g} s warm-up)")
        wall0 = time.time()
        loader.start_event.set()
        await asyncio.sleep(args.warmup)
        cpu0, window0 = [d.cpu_seconds() for d in daphnes], time.time()
        profiler = spawn_profiler(daphne.pid, min(args.duration, 10), args.profile) if args.profile else None
        # Commands during the load: one every COMMAND_PERIOD_S, each on its own (open loop).
        tasks = []
        while time.time() < wall0 + args.warmup + args.duration:
            tasks.append(asyncio.create_task(command_round_trips(http, command, 1, strict=False)))
            await asyncio.sleep(COMMAND_PERIOD_S)
        cpu = [d.cpu_seconds() - before for d, before in zip(daphnes, cpu0, strict=True)]
        cpu_window = time.time() - window0
        loaded = [pair for batch in await asyncio.gather(*tasks) for pair in batch]
        (loaded_report,) = await loop.run_in_executor(None, loader.reports, 120)
        rss, peak = daphne.memory_mib()
    await link.close()
    if "crash" in loaded_report:
        raise RuntimeError(f"the load process crashed: {loaded_report['crash']}")
    if profiler is not None:
        _, err = profiler.communicate(timeout=60)
        if profiler.returncode != 0:
            log(f"py-spy failed: {err.decode(errors='replace')[-500:]}")
        else:
            summarise_profile(args.profile)

    t0, t1 = loaded_report["t0"], loaded_report["t1"]
    per_family = {}
    for family, raw in zip(FAMILIES, loaded_report["samples"], strict=True):
        values = array("d")
        values.frombytes(raw)
        per_family[family] = [v * 1000 for v in values]
    reads = [v for values in per_family.values() for v in values]
    infos = [v for family in INFO_FAMILIES for v in per_family[family]]
    loaded_ms = [lag * 1000 for sent, lag in loaded if t0 <= sent <= t1 and lag is not None]
    loaded_failed = sum(1 for sent, lag in loaded if t0 <= sent <= t1 and lag is None)
    idle_ms = [lag * 1000 for lag in idle]
    elapsed = t1 - t0

    def ms(values: list[float], q: float) -> float | None:
        value = percentile(values, q)
        return None if value is None else round(value, 1)

    return {
        **{f"alone_{family}_p50_ms": ms(values, 50) for family, values in alone.items()},
        "read_p50_ms": ms(reads, 50),
        "read_p99_ms": ms(reads, 99),
        "list_p50_ms": ms(per_family["list"], 50),
        "list_p99_ms": ms(per_family["list"], 99),
        "info_p50_ms": ms(infos, 50),
        "info_p99_ms": ms(infos, 99),
        **{f"{family}_p50_ms": ms(per_family[family], 50) for family in INFO_FAMILIES},
        **{f"{family}_p99_ms": ms(per_family[family], 99) for family in INFO_FAMILIES},
        "reads_per_s": round(len(reads) / elapsed, 1),
        "reads": {family: len(values) for family, values in per_family.items()},
        "read_errors": loaded_report["errors"],
        "list_bytes": loaded_report["sizes"].get(0),
        "command_roundtrip_p50_ms": ms(idle_ms, 50),
        "command_roundtrip_p99_ms": ms(idle_ms, 99),
        "commands": len(idle_ms),
        "command_roundtrip_loaded_p50_ms": ms(loaded_ms, 50),
        "command_roundtrip_loaded_p99_ms": ms(loaded_ms, 99),
        "commands_loaded": len(loaded_ms),
        "commands_loaded_failed": loaded_failed,
        "clients": args.clients,
        "client_rate": args.client_rate,
        "list_share": args.list_share,
        "duration_s": round(elapsed, 1),
        # All processes together (one process: its own share of a core).
        "daphne_cpu_percent": round(100 * sum(cpu) / cpu_window, 1),
        "daphne_cpu_percent_each": [round(100 * c / cpu_window, 1) for c in cpu],
        "daphnes": len(daphnes),
        "daphne_rss_mib": round(rss, 1),
        "daphne_peak_rss_mib": round(peak, 1),
        "client_cpu_percent": round(loaded_report["cpu_percent"], 1),
    }


def fmt(value, unit: str = " ms") -> str:
    return "n/a" if value is None else f"{value:,.1f}{unit}"


def goal(value) -> str:
    if value is None:
        return "n/a"
    return "met" if value <= READ_GOAL_P99_MS else "MISSED"


def summary(r: dict, q: dict) -> None:
    print(
        "\n".join(
            [
                f"fleet: {len(r['fleet'])} robots x {SKILLS} skills x {COMPONENTS} components; "
                f"{r['clients']} concurrent clients for {r['duration_s']} s, "
                + (
                    f"each reading {r['client_rate']:g}/s (open loop, latency from when due), "
                    if r["client_rate"]
                    else "each reading back to back (closed loop: the saturation point), "
                )
                + "GET /api/robot in "
                f"{100 * r['list_share']:.0f}% of reads (thesis Table 3.1 routes; the thesis gives no "
                "latency figure for the Robot API)",
                f"reads: {r['reads_per_s']:,.1f}/s ({r['reads']}), errors {r['read_errors'] or 0}",
                f"all reads p50/p99: {fmt(r['read_p50_ms'])} / {fmt(r['read_p99_ms'])} "
                f"(goal p99 <=50 ms: {goal(r['read_p99_ms'])})",
                f"GET /api/robot ({r['list_bytes'] or 0:,} bytes) p50/p99: {fmt(r['list_p50_ms'])} / "
                f"{fmt(r['list_p99_ms'])} (goal p99 <=50 ms: {goal(r['list_p99_ms'])})",
                f"/info routes p50/p99: {fmt(r['info_p50_ms'])} / {fmt(r['info_p99_ms'])} "
                f"(goal p99 <=50 ms: {goal(r['info_p99_ms'])}); robot {fmt(r['robot_info_p50_ms'])} / "
                f"{fmt(r['robot_info_p99_ms'])}, skill {fmt(r['skill_info_p50_ms'])} / "
                f"{fmt(r['skill_info_p99_ms'])}, component {fmt(r['component_info_p50_ms'])} / "
                f"{fmt(r['component_info_p99_ms'])}",
                f"one client alone, p50: list {fmt(r['alone_list_p50_ms'])}, robot info "
                f"{fmt(r['alone_robot_info_p50_ms'])}, skill info {fmt(r['alone_skill_info_p50_ms'])}, "
                f"component info {fmt(r['alone_component_info_p50_ms'])}",
                f"command round trip (skill start to the robot's ack) p50/p99: idle "
                f"{fmt(r['command_roundtrip_p50_ms'])} / {fmt(r['command_roundtrip_p99_ms'])} "
                f"({r['commands']}), under the read load {fmt(r['command_roundtrip_loaded_p50_ms'])} / "
                f"{fmt(r['command_roundtrip_loaded_p99_ms'])} ({r['commands_loaded']}, "
                f"{r['commands_loaded_failed']} failed) (no goal set)",
                f"queries of GET /api/robot: {q['list_small']} at {SMALL_FLEET} robots, {q['list_full']} at "
                f"{len(r['fleet'])} (goal constant: {'met' if q['list_small'] == q['list_full'] else 'MISSED'}); "
                f"robot info {q['robot_info']}, skill info {q['skill_info']}, component info {q['component_info']}",
                f"daphne: CPU {r['daphne_cpu_percent']:.0f}% of one core, RSS {r['daphne_rss_mib']:.0f} MiB "
                f"(peak {r['daphne_peak_rss_mib']:.0f}); load client CPU {r['client_cpu_percent']:.0f}%",
            ]
        ),
        flush=True,
    )


def main() -> None:
    parser = arguments(
        __doc__, "8 s of load, 50 commands: under a minute in all", database="bridgeos_bench_api", redis=11
    )
    parser.add_argument("--robots", type=int, default=100)
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument(
        "--client-rate",
        type=float,
        default=2.0,
        help="reads per second per client (open loop); 0 sends back to back to find the saturation point",
    )
    parser.add_argument("--duration", type=float, default=20.0, help="measured seconds of read load")
    parser.add_argument("--warmup", type=float, default=2.0, help="seconds of load before measuring")
    parser.add_argument("--list-share", type=float, default=0.1, help="share of reads that are GET /api/robot")
    parser.add_argument("--commands", type=int, default=200, help="sequential command round trips, idle")
    parser.add_argument("--alone", type=int, default=40, help="sequential reads per /info route, one client")
    parser.add_argument("--daphnes", type=int, default=1, help="daphne processes the read clients are spread over")
    parser.add_argument("--profile", metavar="OUT", help="record daphne with py-spy (raw) during the load")
    args = parser.parse_args()
    if args.quick:
        args.duration, args.warmup = min(args.duration, 8.0), 1.0
        args.commands, args.alone = min(args.commands, 50), min(args.alone, 12)
    if args.robots < SMALL_FLEET or args.clients < 1 or args.duration <= 0 or not 0 <= args.list_share <= 1:
        parser.error(f"robots >= {SMALL_FLEET}, clients >= 1, duration > 0, 0 <= list share <= 1")
    if args.daphnes < 1:
        parser.error("daphnes must be at least 1")

    import httpx

    with cloud(args, "bridgeos-bench-api-") as bench:
        logging.getLogger("httpx").setLevel(logging.WARNING)  # Django's config logs every request at INFO
        fleet = prepare(args)
        queries = count_queries(fleet)
        log(
            f"queries of GET /api/robot: {queries['list_small']} at {SMALL_FLEET} robots, {queries['list_full']} at "
            f"{args.robots}"
        )
        daphnes = [bench.start_daphne(f"daphne-{n}.log", wait=False) for n in range(args.daphnes)]
        for each in daphnes:
            each.wait()
            log(f"daphne pid {each.pid} on port {each.port}")
        urls = [f"http://127.0.0.1:{each.port}" for each in daphnes]
        answer = httpx.get(urls[0] + "/api/auth", auth=(OPERATOR, PASSWORD), timeout=30)
        answer.raise_for_status()
        token = answer.json()["token"]
        load_args = {k: getattr(args, k) for k in ("clients", "client_rate", "duration", "warmup", "list_share")}
        loader = Clients(load_main, [urls], token, fleet, load_args)
        try:
            result = asyncio.run(measure(args, daphnes, fleet, token, loader))
        finally:
            loader.kill()
    result["fleet"] = fleet["robots"]
    summary(result, queries)
    del result["fleet"]
    result.update(
        {
            "queries_per_list": queries["list_full"],
            "queries_per_list_small": queries["list_small"],
            "queries_constant": queries["list_small"] == queries["list_full"],
            "queries_robot_info": queries["robot_info"],
            "queries_skill_info": queries["skill_info"],
            "queries_component_info": queries["component_info"],
            "robots": args.robots,
        }
    )
    report(result)


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
