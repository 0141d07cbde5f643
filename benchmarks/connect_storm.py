"""Connect storm: N robots open /ws/robot/ at once against one daphne; time until all are connected.

Every robot authenticates with its own token at the same moment, acks what the cloud sends on
connect, and stays connected. The figure is the time from the first connection attempt until every
robot got `authentication_success` and every robot's row says `connected` in PostgreSQL, and how
many robots were dropped (refused, closed or never answered). Goal (issue 23): 1,000 robots within
5 s, none dropped. The thesis measured one robot at a time.

    .venv/bin/python benchmarks/connect_storm.py --quick
    .venv/bin/python benchmarks/connect_storm.py --robots 1000
"""

from __future__ import annotations

import asyncio
import json
import os
import sys
import time
import uuid
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ROOT, log
from _harness import Clients, arguments, cloud, create_fleet, forget_fleet, report, shares

ROBOT_PREFIX = "storm-"
OWNER = "storm-owner"
NEEDS_ACK = {"connection_established", "robot_config"}


def prepare(robots: int) -> list[tuple[str, str]]:
    """Create the storm's robots afresh, each with its own token; return (id, token) pairs."""
    from django.contrib.auth import get_user_model
    from django.db import connection

    forget_fleet(ROBOT_PREFIX)
    owner, _ = get_user_model().objects.get_or_create(username=OWNER)
    tokens = create_fleet(owner, robots, ROBOT_PREFIX, digits=5, batch_size=1000)
    connection.close()
    return tokens


async def one_robot(url: str, robot_id: str, token: str, start_at: float, hold: asyncio.Event) -> float | None:
    """Connect one robot at ``start_at``; return seconds until authenticated, None if it was dropped."""
    from websockets.asyncio.client import connect

    await asyncio.sleep(max(0.0, start_at - time.time()))
    try:
        async with connect(url, compression=None, ping_interval=None, open_timeout=60, max_size=2**23) as ws:
            auth = {
                "event": "authentication_robot",
                "id": uuid.uuid4().hex,
                "data": {"robot": robot_id, "token": token},
            }
            await ws.send(json.dumps(auth))
            took = None
            while took is None:
                frame = json.loads(await ws.recv())
                if frame["event"] == "authentication_success":
                    took = time.time() - start_at
                elif frame.get("reply_to") == auth["id"]:
                    return None

            async def ack_forever() -> None:
                async for raw in ws:
                    frame = json.loads(raw)
                    if frame["event"] in NEEDS_ACK:
                        await ws.send(json.dumps({"event": "ack", "id": uuid.uuid4().hex, "reply_to": frame["id"]}))

            acking = asyncio.ensure_future(ack_forever())
            await hold.wait()
            if acking.done():
                return None  # the cloud closed this robot's socket while the others connected
            acking.cancel()
            return took
    except Exception:  # refused, reset or timed out: this robot was dropped
        return None


def client_worker(
    index: int,
    tokens: list[tuple[str, str]],
    start_event: Any,
    release: Any,
    queue: Any,
    url: str,
    start_at: float,
    hold_s: float,
) -> None:
    """Run a share of the storm in a process of its own and report each robot's time (None: dropped).

    The robots connect at ``start_at`` and stay connected for ``hold_s`` seconds, or until ``release`` is set.
    """

    async def run() -> list[float | None]:
        hold = asyncio.Event()
        loop = asyncio.get_running_loop()
        loop.call_later(max(0.0, start_at - time.time()) + hold_s, hold.set)
        waiting = loop.run_in_executor(None, release.wait, max(0.0, start_at - time.time()) + hold_s)
        waiting.add_done_callback(lambda _: hold.set())
        return list(await asyncio.gather(*(one_robot(url, rid, tok, start_at, hold) for rid, tok in tokens)))

    queue.put(asyncio.run(run()))


def connected_count() -> int:
    from django.db import connection

    from robots.models import Robot

    try:
        return Robot.objects.filter(id__startswith=ROBOT_PREFIX, connected=True).count()
    finally:
        connection.close()


def storm(
    url: str, tokens: list[tuple[str, str]], *, procs: int = 2, hold_s: float = 20.0, linger_s: float | None = None
) -> dict:
    """Connect every robot to a robot door URL at the same moment, hold them, and return the storm's figures.

    The robots stay ``hold_s`` seconds, or only ``linger_s`` more once all are connected (if given).
    Django must be set up on the storm's database (connected rows are counted there).
    """
    start_at = time.time() + 2.0
    clients = Clients(client_worker, shares(tokens, procs), url, start_at, hold_s)
    all_connected_s = None
    ends_at = start_at + hold_s
    while time.time() < ends_at:
        if all_connected_s is None and connected_count() == len(tokens):
            all_connected_s = time.time() - start_at
            if linger_s is not None:
                ends_at = min(ends_at, time.time() + linger_s)
        time.sleep(0.05)
    clients.stop_event.set()
    times = [took for share in clients.reports(120) for took in share]
    authenticated = sorted(took for took in times if took is not None)
    slowest = authenticated[-1] if authenticated else None
    return {
        "robots": len(tokens),
        # Until every robot was authenticated and its row said connected (None: some never were).
        "connected_s": round(max(slowest, all_connected_s), 2) if slowest and all_connected_s else None,
        "authenticated_p50_s": round(authenticated[len(authenticated) // 2], 3) if authenticated else None,
        "authenticated_max_s": round(slowest, 3) if slowest else None,
        "dropped": len(times) - len(authenticated),
    }


def main() -> None:
    parser = arguments(__doc__, "the same storm, shorter hold: under a minute", database="bridgeos_bench", redis=12)
    parser.add_argument("--robots", type=int, default=1000)
    parser.add_argument("--procs", type=int, default=2, help="client processes opening the sockets")
    parser.add_argument("--hold", type=float, default=20.0, help="seconds the robots stay connected")
    args = parser.parse_args()
    if args.quick:
        args.hold = min(args.hold, 20.0)
    if args.robots < 1 or args.procs < 1:
        parser.error("robots and procs must be positive")

    with cloud(args, "bridgeos-storm-", flush_redis=False) as bench:
        tokens = prepare(args.robots)
        log(f"created {args.robots} robots")
        daphne = bench.start_daphne()
        log(f"daphne pid {daphne.pid} on port {daphne.port}")
        cpu_before = daphne.cpu_seconds()
        result = storm(daphne.ws_url + "/ws/robot/", tokens, procs=args.procs, hold_s=args.hold)
        result["daphne_cpu_s"] = round(daphne.cpu_seconds() - cpu_before, 2)
    log(f"{args.robots} robots: all connected in {result['connected_s']} s, {result['dropped']} dropped")
    report(result)


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
