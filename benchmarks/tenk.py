"""Ten thousand robots on one cloud process: connect, idle, ingest and the API at that size.

One simulated fleet (benchmarks/_multifleet.py: one process multiplexing every robot over the real
wire protocol and authentication) against one daphne sharing one PostgreSQL and one Redis:

- connect: every robot opens /ws/robot/ at the same moment; seconds until all are authenticated
  and every row says `connected`, and how many handshakes or logins were rejected; when the last
  TCP connection opened, the last handshake and the last login were answered (`stages`), and
  daphne's CPU per robot connecting (`connect_daphne_cpu_ms_per_robot`);
- idle: heartbeats only (a WebSocket ping every 5 s, as the agent's default); daphne's CPU, its
  resident memory per robot, and what Redis and PostgreSQL hold per robot;
- ingest: every robot measures 3 points a second and sends them every 5 s in one `metrics` frame
  of 15, as an agent run with `--report-interval 5` does (30,000 points/s, 2,000 frames/s at
  10,000 robots: the cost is per frame, not per point); points stored against points sent, and the
  send-to-ack p95, and the slowest ack of each 5 s (a stall or a growing backlog).
  `--every 1 --points-per-frame 3` is a frame a second per robot;
- the API among them: a robot's reads (p99), a fleet page, a command to one robot (p50) and a
  fleet-wide command; the dashboard's fleet page in Chromium (first render, benchmarks/_fleetpage.py);
- honest presence: some robots vanish without a goodbye; their rows say `disconnected` within
  daphne's ping interval plus timeout.

Beside the fleet, a few real agents (`--agents`, 2; `bridgeos-agent run --simulate --report-interval 5`)
connect to the same daphne once the fleet is in: the reference for what the simulator does. Their
rows must say `connected`, their points be stored (several samples a frame) and a command to each be
answered, as for the simulated robots (`reference_agents` in the last line).

With `--daphnes 2` or `4` the fleet is spread over that many processes, each robot given one's
address in turn; with `--balancer` too, every robot, agent and API call goes through one HAProxy
configured as the stack's (benchmarks/_balancer.py: least connections, WebSockets as tunnels),
whose own CPU is printed beside daphne's (`balancer`).
Goals (issue 37): connect_10k_s <= 10 with 0 rejected, idle_cpu_pct_10k <= 10,
ingest_points_per_s_one_process >= 30,000 at ack p95 <= 1 s, api_p99_ms_10k <= 50, command p50 <= 30 ms.
The simulator's own CPU is printed beside the cloud's. The thesis ran one robot at a time.

    .venv/bin/python benchmarks/tenk.py --quick          # 3,000 robots
    .venv/bin/python benchmarks/tenk.py                  # 10,000 robots
    .venv/bin/python benchmarks/tenk.py --daphnes 2 --balancer
"""

from __future__ import annotations

import asyncio
import logging
import os
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _balancer import Balancer, balancer_capacity
from _common import ROOT, Daphne, ServerProcess, log, percentile
from _fleetpage import fleet_page_first_render_ms
from _harness import arguments, cloud, create_fleet, forget_fleet, report
from _multifleet import FleetProcess

PREFIX = "tenk-"
AGENT_PREFIX = "tenkagent-"  # not matched by PREFIX's LIKE 'tenk-%': the fleet's own counts leave the agents out
OWNER = "tenk-operator"
PASSWORD = "tenk-pass-123"
# daphne's ping window, in which a robot that vanished without a goodbye is found out (shorter with --quick).
PING_INTERVAL_S, PING_TIMEOUT_S = 10, 10
logging.getLogger("httpx").setLevel(logging.WARNING)


def prepare(count: int, agents: int) -> tuple[list[tuple[str, str]], list[tuple[str, str]], str]:
    """Create the fleet and the reference agents' robots afresh, each with a token; return both and an API token."""
    from django.contrib.auth import get_user_model
    from django.db import connection

    from robots.services import issue_api_token

    forget_fleet(PREFIX, metrics=True, events=True)
    forget_fleet(AGENT_PREFIX, metrics=True, events=True)
    with connection.cursor() as cursor:
        # An earlier run's robots leave their pages behind: the per-robot size must be this fleet's.
        cursor.execute("VACUUM FULL robots_robot")
    owner, _ = get_user_model().objects.get_or_create(username=OWNER, defaults={"is_staff": True})
    owner.is_staff = True
    owner.set_password(PASSWORD)
    owner.save()
    tokens = create_fleet(owner, count, PREFIX, digits=5, batch_size=2000)
    agent_tokens = create_fleet(owner, agents, AGENT_PREFIX, digits=2)
    api_token, _ = issue_api_token(owner)
    connection.close()
    return tokens, agent_tokens, api_token


def start_reference_agents(bench: Any, daphne: ServerProcess, agent_tokens: list[tuple[str, str]]) -> list[Any]:
    """Start a real agent for each reference robot, reporting as the simulated fleet does (every 5 s)."""
    agents = []
    for robot_id, token in agent_tokens:
        argv = [str(Path(sys.executable).parent / "bridgeos-agent"), "run", "--master", daphne.ws_url]
        argv += ["--robot", robot_id, "--token", token, "--data-dir", str(bench.data_dir / robot_id)]
        argv += ["--runtime", "process", "--simulate", "--report-interval", "5"]
        agents.append(bench.start_process(robot_id, argv))
    return agents


def reference_agents_report(agent_ids: list[str], api_url: str, api_token: str) -> dict[str, Any]:
    """Check the real agents as the fleet is checked: connected, points stored, samples a frame, commands answered."""
    import httpx

    from monitoring.models import IngestedFrame, Metric
    from robots.models import Robot

    if not agent_ids:
        return {"robots": 0}
    connected = Robot.objects.filter(id__in=agent_ids, connected=True).count()
    points = Metric.objects.filter(robot_id__in=agent_ids).count()
    samples = Metric.objects.filter(robot_id__in=agent_ids).values("robot_id", "ts").distinct().count()
    frames = IngestedFrame.objects.filter(robot_id__in=agent_ids).count()
    answered = 0
    with httpx.Client(base_url=api_url, headers={"Authorization": f"Token {api_token}"}, timeout=30) as http:
        for robot_id in agent_ids:
            answer = http.post(f"/api/robot/{robot_id}/start", params={"wait": "10"})
            answered += answer.status_code == 200 and answer.json().get("accepted") is True
    from django.db import connection

    connection.close()
    return {
        "robots": len(agent_ids),
        "connected": connected,
        "points_stored": points,
        "samples_per_frame": round(samples / frames, 1) if frames else None,
        "commands_answered": answered,
    }


def scalar(sql: str, params: list[Any] | None = None) -> Any:
    from django.db import connection

    with connection.cursor() as cursor:
        cursor.execute(sql, params or [])
        return cursor.fetchone()[0]


def connected_rows() -> int:
    return scalar("SELECT count(*) FROM robots_robot WHERE id LIKE %s AND connected", [PREFIX + "%"])


def stored_points(since: float) -> int:
    from monitoring.models import Metric

    return scalar(
        f"SELECT count(*) FROM {Metric._meta.db_table} WHERE robot_id LIKE %s AND ts >= to_timestamp(%s)",
        [PREFIX + "%", since],
    )


def redis_used(url: str) -> int:
    import redis

    return int(redis.Redis.from_url(url).info("memory")["used_memory"])


def postgres_bytes_per_robot(robots: int) -> float:
    """Return what the fleet's own rows take in PostgreSQL per robot: the robots table and its indexes."""
    return scalar("SELECT pg_total_relation_size('robots_robot')") / max(1, robots)


def cpu_pct(daphnes: list[Daphne], before: list[float], seconds: float) -> list[float]:
    return [round(100 * (d.cpu_seconds() - b) / seconds, 1) for d, b in zip(daphnes, before, strict=True)]


# --------------------------------------------------------------------------- the phases


def machine_busy() -> tuple[float, float]:
    """Return the machine's busy and total CPU time so far, in clock ticks of all cores (/proc/stat)."""
    fields = [float(value) for value in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle and iowait
    return sum(fields) - idle, sum(fields)


def connect_phase(fleet: FleetProcess, daphnes: list[Daphne], timeout: float) -> dict[str, Any]:
    """Open every robot at once; the figure ends when all are authenticated and their rows say connected."""
    machine_before = machine_busy()
    daphne_before = [d.cpu_seconds() for d in daphnes]
    began = time.monotonic()
    answer = fleet.ask("connect", timeout=timeout + 30, within_s=timeout)
    rows_at = None
    while time.monotonic() - began < timeout + 10:
        if connected_rows() >= answer["connected"]:
            rows_at = time.monotonic() - began
            break
        time.sleep(0.1)
    connect_s = None
    if answer["connect_s"] is not None and rows_at is not None:
        connect_s = round(max(answer["connect_s"], rows_at), 2)
    busy, total = (after - before for after, before in zip(machine_busy(), machine_before, strict=True))
    # The whole machine's share in use: the fleet, daphne, PostgreSQL, Redis and the kernel's TCP work together.
    machine_pct = round(100 * busy / total, 1) if total else None
    # daphne's own CPU per robot: steadier than the wall time on a shared machine, and what the changes cut.
    daphne_cpu_s = sum(d.cpu_seconds() - before for d, before in zip(daphnes, daphne_before, strict=True))
    return {
        **answer,
        "daphne_cpu_ms_per_robot": round(1000 * daphne_cpu_s / max(1, answer["connected"]), 3),
        "connect_s": connect_s,
        "simulator_cpu_pct": fleet.cpu_pct(answer),
        "machine_cpu_pct": machine_pct,
    }


def idle_phase(fleet: FleetProcess, daphnes: list[Daphne], seconds: float) -> dict[str, Any]:
    before = [d.cpu_seconds() for d in daphnes]
    answer = fleet.ask("idle", seconds=seconds)
    return {"daphne_cpu_pct": cpu_pct(daphnes, before, answer["wall_s"]), "simulator_cpu_pct": fleet.cpu_pct(answer)}


def ingest_phase(
    fleet: FleetProcess, daphnes: list[Daphne], robots: int, points_per_frame: int, every_s: float, seconds: float
) -> dict[str, Any]:
    """Every robot sends a frame of ``points_per_frame`` every ``every_s``; count what is stored and the acks' lag."""
    since = time.time() - 1
    before = [d.cpu_seconds() for d in daphnes]
    answer = fleet.ask("ingest", seconds=seconds, points_per_frame=points_per_frame, every_s=every_s, drain_s=3.0)
    daphne_cpu = cpu_pct(daphnes, before, answer["wall_s"])
    latencies = answer["latencies"]
    stored = stored_points(since)
    offered = robots * points_per_frame / every_s
    p95 = percentile(latencies, 95)
    return {
        "offered_points_per_s": round(offered),
        "points_sent": answer["points_sent"],
        "points_stored": stored,
        "stored_per_s": round(stored / seconds),
        "ack_p50_ms": round(1000 * (percentile(latencies, 50) or 0), 1),
        "ack_p95_ms": round(1000 * (p95 or 0), 1),
        "unacked_frames": answer["unacked_frames"],
        # The slowest ack of each 5 s (by when it came): a stall shows as one window, a backlog as a climb.
        "ack_max_ms_by_5s": slowest_by_window(answer["acked_after_s"], latencies, 5.0),
        "daphne_cpu_pct": daphne_cpu,
        "simulator_cpu_pct": fleet.cpu_pct(answer),
    }


def slowest_by_window(moments: list[float], latencies: list[float], window_s: float) -> list[float]:
    """Return the longest latency among those that ended in each window of ``window_s`` seconds, in ms."""
    slowest: dict[int, float] = {}
    for moment, latency in zip(moments, latencies, strict=True):
        window = int(moment // window_s)
        slowest[window] = max(slowest.get(window, 0.0), latency)
    return [round(1000 * slowest.get(window, 0.0)) for window in range(max(slowest, default=-1) + 1)]


async def api_phase(daphne: ServerProcess, api_token: str, robots: list[str], samples: int) -> dict[str, Any]:
    """Time the Robot API among the fleet: a robot's reads, a fleet page, a command to one robot, a fleet command."""
    import httpx

    headers = {"Authorization": f"Token {api_token}"}
    reads: list[float] = []
    pages: list[float] = []
    commands: list[float] = []
    failed: list[str] = []  # commands not answered (an overloaded process after the ingest phase)
    step = max(1, len(robots) // samples)
    async with httpx.AsyncClient(base_url=f"http://127.0.0.1:{daphne.port}", headers=headers, timeout=60) as http:
        for warm in robots[:5]:
            await http.get(f"/api/robot/{warm}")
        for robot in robots[::step][:samples]:
            started = time.perf_counter()
            response = await http.get(f"/api/robot/{robot}")
            reads.append(1000 * (time.perf_counter() - started))
            response.raise_for_status()
        for offset in range(0, min(len(robots), 100 * samples), max(100, len(robots) // samples))[:samples]:
            started = time.perf_counter()
            response = await http.get("/api/robot", params={"limit": 100, "offset": offset})
            pages.append(1000 * (time.perf_counter() - started))
            response.raise_for_status()
        for robot in robots[::step][: max(20, samples // 5)]:
            started = time.perf_counter()
            response = await http.post(f"/api/robot/{robot}/start", params={"wait": "5"})
            commands.append(1000 * (time.perf_counter() - started))
            if response.status_code != 200 or not response.json().get("accepted"):
                failed.append(f"{robot}: {response.status_code} {response.text[:200]}")
        started = time.perf_counter()
        response = await http.post("/api/robot/start", params={"wait": "30"}, timeout=120)
        fleet_ms = 1000 * (time.perf_counter() - started)
        response.raise_for_status()
        body = response.json()
    accepted = sum(1 for answer in body["results"] if answer.get("accepted"))
    return {
        "read_p50_ms": round(percentile(reads, 50) or 0, 1),
        "read_p99_ms": round(percentile(reads, 99) or 0, 1),
        "page_p50_ms": round(percentile(pages, 50) or 0, 1),
        "page_p99_ms": round(percentile(pages, 99) or 0, 1),
        "command_p50_ms": round(percentile(commands, 50) or 0, 1),
        "command_p95_ms": round(percentile(commands, 95) or 0, 1),
        "fleet_command_ms": round(fleet_ms),
        "fleet_command_accepted": accepted,
        "command_failures": len(failed),
        "command_failure_example": failed[0] if failed else None,
    }


def vanish_phase(fleet: FleetProcess, how_many: int, within_s: float) -> dict[str, Any]:
    """Make robots vanish without a goodbye; time until their rows say disconnected."""
    from robots.models import Robot

    gone = fleet.ask("vanish", robots=how_many)["robots"]
    began = time.monotonic()
    still = len(gone)
    while time.monotonic() - began < within_s:
        still = Robot.objects.filter(id__in=gone, connected=True).count()
        if still == 0:
            break
        time.sleep(0.5)
    return {"vanished": len(gone), "still_connected": still, "disconnected_after_s": round(time.monotonic() - began, 1)}


class BalancerCpu:
    """HAProxy's CPU over each phase: ms a robot while connecting, % of a core otherwise."""

    def __init__(self, balancer: Balancer | None) -> None:
        self.balancer = balancer
        self.figures: dict[str, float] = {}
        self._since = (balancer.cpu_seconds(), time.monotonic()) if balancer is not None else (0.0, 0.0)

    def phase(self, name: str | None = None, *, per: int | None = None) -> None:
        """End a phase begun at the last call, naming its figure (none: a gap not measured)."""
        if self.balancer is None:
            return
        cpu, at = self.balancer.cpu_seconds(), time.monotonic()
        if name is not None:
            used, wall = cpu - self._since[0], at - self._since[1]
            value = 1000 * used / max(1, per) if per is not None else 100 * used / max(wall, 1e-9)
            self.figures[name] = round(value, 3 if per is not None else 1)
        self._since = (cpu, at)


# --------------------------------------------------------------------------- main


def main() -> None:
    parser = arguments(__doc__, "3,000 robots, short phases: under a minute", database="bridgeos_tenk", redis=13)
    parser.add_argument("--robots", type=int, default=None, help="robots in the fleet (10,000; 3,000 with --quick)")
    parser.add_argument("--daphnes", type=int, default=1, help="daphne processes the fleet is spread over")
    parser.add_argument("--points-per-frame", type=int, default=15)
    parser.add_argument("--every", type=float, default=5.0, help="seconds between a robot's metric frames")
    parser.add_argument("--ingest-s", type=float, default=None)
    parser.add_argument("--idle-s", type=float, default=None)
    parser.add_argument("--skip-vanish", action="store_true")
    parser.add_argument("--agents", type=int, default=2, help="real agents beside the fleet, the reference (2)")
    parser.add_argument("--balancer", action="store_true", help="HAProxy in front of the daphnes, as in the stack")
    args = parser.parse_args()
    robots = args.robots or (3000 if args.quick else 10_000)
    if args.balancer and robots + args.agents > balancer_capacity():
        parser.error(
            f"--balancer: HAProxy holds at most {balancer_capacity()} connections under this machine's limit on"
            f" open files (two each); run fewer --robots"
        )
    ingest_s = args.ingest_s or (10.0 if args.quick else 30.0)
    idle_s = args.idle_s or (5.0 if args.quick else 20.0)
    ping_s, ping_timeout_s = (5, 5) if args.quick else (PING_INTERVAL_S, PING_TIMEOUT_S)
    env = {"BRIDGEOS_WS_PING_INTERVAL": str(ping_s), "BRIDGEOS_WS_PING_TIMEOUT": str(ping_timeout_s)}

    with cloud(args, "bridgeos-tenk-", env=env) as bench:
        tokens, agent_tokens, api_token = prepare(robots, args.agents)
        ids = [robot_id for robot_id, _ in tokens]
        log(f"created {robots} robots")
        daphnes = [bench.start_daphne(f"daphne-{i}.log", wait=False) for i in range(args.daphnes)]
        for daphne in daphnes:
            daphne.wait()
        balancer = Balancer(daphnes, bench.data_dir) if args.balancer else None
        if balancer is not None:
            balancer.wait()
        front: ServerProcess = balancer or daphnes[0]  # where the agents, the API and the browser go
        redis_before = redis_used(args.redis_url)
        rss_before = [d.memory_mib()[0] for d in daphnes]
        fleet = FleetProcess(tokens, [front.ws_url] if balancer else [d.ws_url for d in daphnes])
        balancer_cpu = BalancerCpu(balancer)
        try:
            connected = connect_phase(fleet, daphnes, timeout=60)
            balancer_cpu.phase("connect_cpu_ms_per_robot", per=connected["connected"])
            log(f"connect: {connected}")
            # The real agents join once the fleet is in: the connect figure is the fleet's own.
            start_reference_agents(bench, front, agent_tokens)
            time.sleep(2.0)
            balancer_cpu.phase()
            idle = idle_phase(fleet, daphnes, idle_s)
            balancer_cpu.phase("idle_cpu_pct")
            rss_after = [d.memory_mib()[0] for d in daphnes]
            kb_per_robot = round(1024 * sum(a - b for a, b in zip(rss_after, rss_before, strict=True)) / robots, 1)
            redis_kb = round((redis_used(args.redis_url) - redis_before) / 1024 / robots, 2)
            postgres_kb = round(postgres_bytes_per_robot(robots) / 1024, 2)
            log(f"idle: {idle}, {kb_per_robot} KiB/robot in daphne, {redis_kb} in Redis, {postgres_kb} in PostgreSQL")
            balancer_cpu.phase()
            ingest = ingest_phase(fleet, daphnes, robots, args.points_per_frame, args.every, ingest_s)
            balancer_cpu.phase("ingest_cpu_pct")
            log(f"ingest: {ingest}")
            api = asyncio.run(api_phase(front, api_token, ids, 100 if args.quick else 500))
            log(f"api: {api}")
            # The dashboard's fleet page, as an operator who sees the whole fleet opens it, every robot connected.
            page = fleet_page_first_render_ms(f"http://127.0.0.1:{front.port}", OWNER, PASSWORD, samples=3)
            log(f"fleet page: {page}")
            agents = reference_agents_report(
                [robot_id for robot_id, _ in agent_tokens], f"http://127.0.0.1:{front.port}", api_token
            )
            log(f"reference agents: {agents}")
            vanish = None
            if not args.skip_vanish:
                vanish = vanish_phase(fleet, max(1, robots // 100), ping_s + ping_timeout_s + 10)
                log(f"vanish: {vanish}")
            state = fleet.ask("state")
        finally:
            fleet.stop()
            if balancer is not None:
                balancer.stop()
    ingest_ok = ingest["ack_p95_ms"] <= 1000 and ingest["points_stored"] >= ingest["points_sent"]
    report(
        {
            "robots": robots,
            "daphnes": args.daphnes,
            "connect_10k_s": connected["connect_s"],
            "connect_10k_rejected": connected["rejected"],
            "connect_daphne_cpu_ms_per_robot": connected["daphne_cpu_ms_per_robot"],
            "connect_failures": connected["failures"],
            "idle_cpu_pct_10k": round(sum(idle["daphne_cpu_pct"]), 1),
            "kb_per_robot": kb_per_robot,
            "redis_kb_per_robot": redis_kb,
            "postgres_kb_per_robot": postgres_kb,
            "ingest_points_per_s_one_process": ingest["stored_per_s"] if ingest_ok else 0,
            "ingest": ingest,
            "api_p99_ms_10k": api["read_p99_ms"],
            "api": api,
            "fleet_page_first_render_ms": page["first_render_ms_p50"],
            "vanish": vanish,
            "reference_agents": agents,
            "closed_after_auth": state["closed_after_auth"],
            "balancer": balancer_cpu.figures if balancer is not None else None,
            "simulator_cpu_pct": max(
                connected["simulator_cpu_pct"], idle["simulator_cpu_pct"], ingest["simulator_cpu_pct"]
            ),
            "simulator_cpu_pct_by_phase": {
                "connect": connected["simulator_cpu_pct"],
                "idle": idle["simulator_cpu_pct"],
                "ingest": ingest["simulator_cpu_pct"],
            },
        }
    )


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
