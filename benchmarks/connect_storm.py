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

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import sys
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ROOT, Daphne, ensure_postgres_database, log, migrate, setup_django

ROBOT_PREFIX = "storm-"
OWNER = "storm-owner"
NEEDS_ACK = {"connection_established", "robot_config"}


def prepare(robots: int) -> list[tuple[str, str]]:
    """Create the storm's robots afresh, each with its own token; return (id, token) pairs."""
    from django.contrib.auth import get_user_model
    from django.db import connection

    from robots.models import Robot, default_robot_config

    Robot.objects.filter(id__startswith=ROBOT_PREFIX).delete()
    owner, _ = get_user_model().objects.get_or_create(username=OWNER)
    config = default_robot_config()
    rows, tokens = [], []
    for i in range(robots):
        robot = Robot(id=f"{ROBOT_PREFIX}{i:05d}", owner=owner, config=config)
        tokens.append((robot.id, robot.issue_token()))
        rows.append(robot)
    Robot.objects.bulk_create(rows, batch_size=1000)
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
    url: str, tokens: list[tuple[str, str]], start_at: float, hold_s: float, queue: mp.Queue, release: Any = None
) -> None:
    """Run a share of the storm in a process of its own and report each robot's time (None: dropped).

    The robots stay connected for ``hold_s`` seconds, or until ``release`` (an mp.Event) is set.
    """

    async def run() -> list[float | None]:
        hold = asyncio.Event()
        loop = asyncio.get_running_loop()
        loop.call_later(max(0.0, start_at - time.time()) + hold_s, hold.set)
        if release is not None:
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
    queue: mp.Queue = mp.Queue()
    release = mp.Event()
    shares = [tokens[i::procs] for i in range(procs)]
    workers = [
        mp.Process(target=client_worker, args=(url, share, start_at, hold_s, queue, release)) for share in shares
    ]
    for worker in workers:
        worker.start()
    all_connected_s = None
    ends_at = start_at + hold_s
    while time.time() < ends_at:
        if all_connected_s is None and connected_count() == len(tokens):
            all_connected_s = time.time() - start_at
            if linger_s is not None:
                ends_at = min(ends_at, time.time() + linger_s)
        time.sleep(0.05)
    release.set()
    times = [took for _ in workers for took in queue.get(timeout=120)]
    for worker in workers:
        worker.join(timeout=30)
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
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--robots", type=int, default=1000)
    parser.add_argument("--quick", action="store_true", help="the same storm, shorter hold: under a minute")
    parser.add_argument("--procs", type=int, default=2, help="client processes opening the sockets")
    parser.add_argument("--hold", type=float, default=20.0, help="seconds the robots stay connected")
    parser.add_argument("--database-url", default="postgres://postgres@127.0.0.1:5432/bridgeos_bench")
    parser.add_argument("--redis-url", default="redis://127.0.0.1:6379/12")
    args = parser.parse_args()
    if args.quick:
        args.hold = min(args.hold, 20.0)
    if args.robots < 1 or args.procs < 1:
        parser.error("robots and procs must be positive")

    data_dir = tempfile.mkdtemp(prefix="bridgeos-storm-")
    env = {"DATABASE_URL": args.database_url, "REDIS_URL": args.redis_url, "BRIDGEOS_DATA_DIR": data_dir}
    ensure_postgres_database(args.database_url)
    migrate(env)
    setup_django(env)
    tokens = prepare(args.robots)
    log(f"created {args.robots} robots")

    daphne = Daphne(env, Path(data_dir) / "daphne.log")
    try:
        daphne.wait()
        log(f"daphne pid {daphne.pid} on port {daphne.port}")
        cpu_before = daphne.cpu_seconds()
        result = storm(daphne.ws_url + "/ws/robot/", tokens, procs=args.procs, hold_s=args.hold)
        result["daphne_cpu_s"] = round(daphne.cpu_seconds() - cpu_before, 2)
    except BaseException:
        log(f"daphne log tail:\n{daphne.log_tail()}")
        raise
    finally:
        daphne.stop()
    log(f"{args.robots} robots: all connected in {result['connected_s']} s, {result['dropped']} dropped")
    print(json.dumps(result), flush=True)


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
