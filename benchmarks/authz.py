"""Authorization and audit: the Robot API's reads with organizations and roles, and the audit trail's speed.

The read mix of benchmarks/api_load.py (100 robots x 5 skills x 5 components, 50 clients at
2 reads/s each, 10% GET /api/robot) runs as a member of the fleet's organization (an operator
there, a viewer in three others; more organizations and members around) and as a staff user,
who skips the membership filter and every role check: the same load without the role checks.
The two run at once, half the clients each, so whatever else the machine does hits both. Meanwhile
commands arrive at 10/s (robot stop to offline robots, each one audit entry). Then the audit trail
alone: entries written by concurrent writers through the recording service, and the verify walk.
Last, the role matrix of tests/teams/matrix.py: every route and WebSocket door, read from the
routing, as every role and none, on the caller's organization and another's, each status exact.

    .venv/bin/python benchmarks/authz.py --quick
    .venv/bin/python benchmarks/authz.py
"""

from __future__ import annotations

import logging
import os
import sys
import threading
import time
from array import array
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _api_load_reads import FAMILIES, load_main
from _common import ROOT, log, percentile
from _harness import Clients, arguments, cloud, create_fleet, machine_load, report

PREFIX = "authz-bench-"
ORGANIZATION = "authz-bench-fleet"
MEMBER = "authz-bench-member"
STAFF = "authz-bench-staff"
OTHERS = 3  # organizations the member is a viewer of, two robots each
STRANGERS = 3  # organizations the member is not in, with members of their own
GOAL_RATIO = 1.1
COMMANDS_PER_S = 10.0


def prepare(args: Any) -> dict[str, Any]:
    """Replace earlier bench data: the fleet's organization, the others, the member and staff, and their tokens."""
    from api_load import skill_configs
    from django.contrib.auth import get_user_model

    from robots.models import Robot
    from robots.services import issue_api_token
    from teams.models import Membership, Organization

    started = time.monotonic()
    Robot.objects.filter(id__startswith=PREFIX).delete()
    User = get_user_model()
    User.objects.filter(username__startswith=PREFIX).delete()
    Organization.objects.filter(slug__startswith=PREFIX).delete()
    member = User.objects.create_user(MEMBER)
    staff = User.objects.create_user(STAFF, is_staff=True)
    fleet_org = Organization.objects.create(slug=ORGANIZATION)
    Membership.objects.create(organization=fleet_org, user=member, role="operator")
    configs = skill_configs()
    tokens = create_fleet(member, args.robots, PREFIX, named=True, skills=configs, organization=fleet_org)
    for index in range(OTHERS + STRANGERS):
        other = Organization.objects.create(slug=f"{PREFIX}org-{index}")
        colleague = User.objects.create_user(f"{PREFIX}user-{index}")
        Membership.objects.create(organization=other, user=colleague, role="admin")
        Membership.objects.create(organization=fleet_org, user=colleague, role="viewer")
        if index < OTHERS:
            # Both readers see these robots, so both lists are the same size.
            Membership.objects.create(organization=other, user=member, role="viewer")
            create_fleet(colleague, 2, f"{PREFIX}o{index}-", named=True, organization=other)
    elapsed = time.monotonic() - started
    log(f"created {args.robots} robots and {OTHERS + STRANGERS} more organizations in {elapsed:.1f} s")
    return {
        "robots": [robot_id for robot_id, _ in tokens],
        "skills": [c["skill_id"] for c in configs],
        "components": list(configs[0]["components"]),
        "member_token": issue_api_token(member)[0],
        "staff_token": issue_api_token(staff)[0],
    }


def commands(url: str, token: str, robots: list[str], stop: threading.Event, sent: list[int]) -> None:
    """Send robot commands at COMMANDS_PER_S (the robots are offline: answered at once, audited each)."""
    import httpx

    with httpx.Client(base_url=url, headers={"Authorization": f"Token {token}"}, timeout=30) as http:
        due = time.monotonic()
        index = 0
        while not stop.is_set():
            http.post(f"/api/robot/{robots[index % len(robots)]}/stop")
            index += 1
            sent[0] += 1
            # Never a burst to catch up after a slow answer: the rate stays at most COMMANDS_PER_S.
            due = max(due + 1 / COMMANDS_PER_S, time.monotonic())
            time.sleep(max(0.0, due - time.monotonic()))


def read_phase(url: str, fleet: dict[str, Any], load_args: dict[str, Any]) -> dict[str, tuple[list[float], dict, dict]]:
    """Run the read mix as the member and as staff at once, half the clients each.

    Return each caller's latencies (ms), errors and latencies by family. Both meet the same queue
    at the same moment, so what the machine does meanwhile cannot favour either.
    """
    half = {**load_args, "clients": max(1, load_args["clients"] // 2)}
    loaders = {who: Clients(load_main, [[url]], fleet[f"{who}_token"], fleet, half) for who in ("member", "staff")}
    try:
        for loader in loaders.values():
            loader.start_event.set()
        reports = {who: loader.reports(120)[0] for who, loader in loaders.items()}
    finally:
        for loader in loaders.values():
            loader.kill()
    answers = {}
    for who, result in reports.items():
        if "crash" in result:
            raise RuntimeError(f"the {who} load process crashed: {result['crash']}")
        latencies: list[float] = []
        families: dict[str, list[float]] = {}
        for family, raw in zip(FAMILIES, result["samples"], strict=True):
            values = array("d")
            values.frombytes(raw)
            families[family] = [v * 1000 for v in values]
            latencies += families[family]
        answers[who] = (latencies, result["errors"], families)
    return answers


def in_process_costs(fleet: dict[str, Any], rounds: int) -> dict[str, float]:
    """Time the read mix's four routes in-process (no server, no queueing) as member and as staff; p50 ms each.

    Under a busy machine the loaded p99s mostly measure the queue; this is each request's own cost.
    """
    from django.test import Client

    robot, skill, component = fleet["robots"][3], fleet["skills"][1], fleet["components"][1]
    paths = [
        "/api/robot",
        f"/api/robot/{robot}/info",
        f"/api/robot/{robot}/skill/{skill}/info",
        f"/api/robot/{robot}/skill/{skill}/component/{component}/info",
    ]
    clients = {
        who: Client(SERVER_NAME="localhost", HTTP_AUTHORIZATION=f"Token {fleet[f'{who}_token']}")
        for who in ("member", "staff")
    }
    times: dict[str, list[float]] = {"member": [], "staff": []}
    for round_ in range(rounds + 2):
        for who, http in clients.items():
            for path in paths:
                began = time.perf_counter()
                response = http.get(path)
                if response.status_code != 200:
                    raise RuntimeError(f"{who} GET {path} answered {response.status_code}")
                if round_ >= 2:  # the first two rounds warm caches up
                    times[who].append(1000 * (time.perf_counter() - began))
    return {who: percentile(values, 50) or 0.0 for who, values in times.items()}


def write_rate(rows: int, writers: int) -> float:
    """Write entries through the recording service from concurrent threads; return rows per second."""
    from django.db import connection

    from audit import services

    def writer(count: int) -> None:
        try:
            for index in range(count):
                services.record(
                    "robot.stop", door="rest", actor=MEMBER, token="bench", target=f"robot/{PREFIX}{index}", status=409
                )
        finally:
            connection.close()

    threads = [threading.Thread(target=writer, args=(rows // writers,)) for _ in range(writers)]
    started = time.perf_counter()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return (rows // writers) * writers / (time.perf_counter() - started)


def verify_rate() -> tuple[float, int]:
    """Walk the whole chain as `manage.py audit verify` does; return rows per second and rows."""
    from audit import services

    started = time.perf_counter()
    result = services.verify_chain()
    if result.broken is not None:
        raise RuntimeError(f"the audit chain is broken at {result.broken}")
    return result.rows / (time.perf_counter() - started), result.rows


def role_matrix(port: int) -> dict[str, Any]:
    """Run the project's role matrix on the benchmark's cloud, its WebSocket doors through the running daphne."""
    sys.path.insert(0, str(ROOT))
    from tests.teams.matrix import run_matrix

    logging.getLogger("django.request").setLevel(logging.ERROR)  # the matrix's 403s and 404s are expected
    return run_matrix(f"ws://127.0.0.1:{port}")


def main() -> None:
    parser = arguments(
        __doc__, "4 phases of 3.5 s, 1500 audit rows: under a minute", database="bridgeos_bench_authz", redis=12
    )
    parser.add_argument("--robots", type=int, default=100)
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--client-rate", type=float, default=2.0, help="reads per second per client (open loop)")
    parser.add_argument("--phase", type=float, default=10.0, help="measured seconds of each phase")
    parser.add_argument("--rounds", type=int, default=3, help="member and staff phases, alternating, each this often")
    parser.add_argument("--audit-rows", type=int, default=20000, help="entries the writers write")
    parser.add_argument("--writers", type=int, default=8, help="concurrent audit writers")
    args = parser.parse_args()
    if args.quick:
        args.phase, args.rounds, args.audit_rows = 5.0, 1, 1500
    if args.robots < 1 or args.clients < 1 or args.phase <= 0 or args.rounds < 1 or args.writers < 1:
        parser.error("robots, clients, rounds and writers >= 1, phase > 0")

    with cloud(args, "bridgeos-bench-authz-") as bench:
        logging.getLogger("httpx").setLevel(logging.WARNING)
        fleet = prepare(args)
        costs = in_process_costs(fleet, 10 if args.quick else 50)
        log(f"in-process read p50: member {costs['member']:.1f} ms, staff {costs['staff']:.1f} ms")
        daphne = bench.start_daphne()
        url = f"http://127.0.0.1:{daphne.port}"
        load_args = {"clients": args.clients, "client_rate": args.client_rate, "duration": args.phase}
        load_args |= {"warmup": 1.0, "list_share": 0.1}
        stop, sent = threading.Event(), [0]
        commander = threading.Thread(target=commands, args=(url, fleet["member_token"], fleet["robots"], stop, sent))
        commander.start()
        reads: dict[str, list[float]] = {"member": [], "staff": []}
        by_family: dict[str, list[float]] = {}
        errors: dict[str, dict] = {"member": {}, "staff": {}}
        # Unmeasured: daphne's imports, connections and caches warm up for both callers first.
        read_phase(url, fleet, {**load_args, "duration": 3.0})
        log(machine_load())
        started, sent_before = time.monotonic(), sent[0]
        try:
            for _ in range(args.rounds):
                # Twice a phase: each caller has half the clients, so as many reads as a phase alone.
                for who, (latencies, failed, families) in read_phase(
                    url, fleet, {**load_args, "duration": 2 * args.phase}
                ).items():
                    reads[who] += latencies
                    for family, values in families.items():
                        by_family.setdefault(f"{who}_{family}", []).extend(values)
                    for key, count in failed.items():
                        errors[who][key] = errors[who].get(key, 0) + count
                    log(f"{who}: {len(latencies)} reads, p99 {percentile(latencies, 99):.1f} ms")
        finally:
            stop.set()
            commander.join()
        command_rate = (sent[0] - sent_before) / (time.monotonic() - started)
        rows_per_s = write_rate(args.audit_rows, args.writers)
        log(f"audit: {args.audit_rows} rows by {args.writers} writers at {rows_per_s:,.0f}/s")
        verify_per_s, verified = verify_rate()
        log(f"audit verify: {verified} rows at {verify_per_s:,.0f}/s")
        matrix = role_matrix(daphne.port)
        log(f"role matrix: {matrix['cases']} cases, {matrix['violations']} violations {matrix['failed'][:5]}")

    member_p99, staff_p99 = percentile(reads["member"], 99), percentile(reads["staff"], 99)
    ratio = None if not member_p99 or not staff_p99 else member_p99 / staff_p99
    print(
        f"reads as a member (roles checked) p50/p99: {percentile(reads['member'], 50):.1f} / {member_p99:.1f} ms; "
        f"as staff (no role checks) {percentile(reads['staff'], 50):.1f} / {staff_p99:.1f} ms; "
        f"p99 ratio {ratio:.2f} (goal <= {GOAL_RATIO}: {'met' if ratio and ratio <= GOAL_RATIO else 'MISSED'}), "
        f"with {command_rate:.1f} audited commands/s\n"
        f"audit: {rows_per_s:,.0f} rows/s written by {args.writers} writers; verify {verify_per_s:,.0f} rows/s "
        f"over {verified} rows\n"
        f"role matrix: {matrix['cases']} cases, {matrix['violations']} violations (goal 0)",
        flush=True,
    )
    report(
        {
            "api_p99_over_before": None if ratio is None else round(ratio, 3),
            "member_read_p50_ms": round(percentile(reads["member"], 50), 1),
            "member_read_p99_ms": round(member_p99, 1),
            "staff_read_p50_ms": round(percentile(reads["staff"], 50), 1),
            "staff_read_p99_ms": round(staff_p99, 1),
            "reads": {who: len(values) for who, values in reads.items()},
            **{f"{key}_p50_ms": round(percentile(values, 50) or 0.0, 1) for key, values in by_family.items()},
            # Each read's own cost in-process, without the server's queue: robust on a busy machine.
            "member_inprocess_p50_ms": round(costs["member"], 2),
            "staff_inprocess_p50_ms": round(costs["staff"], 2),
            "inprocess_over_before": round(costs["member"] / costs["staff"], 3) if costs["staff"] else None,
            "read_errors": errors,
            "audited_commands_per_s": round(command_rate, 1),
            "audit_rows_per_s": round(rows_per_s, 1),
            "audit_writers": args.writers,
            "audit_verify_rows_per_s": round(verify_per_s, 1),
            "audit_verified_rows": verified,
            "role_matrix_cases": matrix["cases"],
            "role_matrix_violations": matrix["violations"],
            "robots": args.robots,
            "families": list(FAMILIES),
        }
    )


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
