"""Restart the cloud's stores under a streaming fleet: a private Redis, then a private PostgreSQL.

The cloud (daphne) runs against a redis-server and a PostgreSQL cluster of this scenario's own
(own ports, temp dirs), so breaking them touches nobody else. Redis is killed and stays down (the
channel layer and the Celery broker gone), then comes back empty; PostgreSQL is stopped with
`pg_ctl -m immediate` (every connection dropped mid-statement, the metric writer's COPY among
them) and started again. Every point a robot made must be stored exactly once; the time to
recover is from the store's return until every point made before it is stored.
"""

from __future__ import annotations

import shutil
import sys
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from benchmarks.chaos import Outcome
from benchmarks.chaos.rig import (
    Cloud,
    CloudServer,
    Fleet,
    PrivatePostgres,
    PrivateRedis,
    count_stored,
    create_robots,
    scratch_dir,
    wait_until,
)

NAME = "stores"
INJECTS = "private Redis killed and down (channel layer + broker), private PostgreSQL stopped -m immediate mid-COPY"
# Every point made before the store's return stored within this long of it.
RECOVER_GOAL_S = 15.0


def run(quick: bool) -> list[Outcome]:
    """Break Redis, then PostgreSQL, each under a fleet of its own; one outcome each."""
    workdir = scratch_dir(NAME)
    redis = PrivateRedis(workdir)
    postgres = PrivatePostgres(workdir)
    cloud: Cloud | None = None
    try:
        redis.start()
        postgres.init()
        postgres.start()
        cloud = Cloud(NAME, database=postgres.url, redis=redis.url)
        cloud.start()
        env = cloud.env
        robots = 10 if quick else 50
        pairs = create_robots(env, f"chaos-st-{uuid.uuid4().hex[:6]}", 2 * robots)
        faults: list[tuple[str, float, Callable[[], None], Callable[[], None]]] = [
            ("Redis killed", 4.0 if quick else 10.0, redis.kill, redis.start),
            (
                "PostgreSQL stopped -m immediate",
                3.0 if quick else 10.0,
                lambda: postgres.stop("immediate"),
                postgres.start,
            ),
        ]
        return [
            _break_store(
                f"{what}, down {down_s:.0f} s, {robots} robots streaming",
                env,
                cloud.server,
                workdir / f"fleet-{n}",
                pairs[n * robots : (n + 1) * robots],
                stream_s=2.0 if quick else 10.0,
                down_s=down_s,
                stop=stop,
                start=start,
            )
            for n, (what, down_s, stop, start) in enumerate(faults)
        ]
    finally:
        if cloud is not None:
            cloud.stop()
            shutil.rmtree(cloud.dir, ignore_errors=True)
        redis.stop()
        postgres.stop("immediate")
        shutil.rmtree(workdir, ignore_errors=True)


def _break_store(
    injected: str,
    env: dict[str, str],
    cloud: CloudServer,
    fleet_dir: Path,
    pairs: list[tuple[str, str]],
    *,
    stream_s: float,
    down_s: float,
    stop: Callable[[], None],
    start: Callable[[], None],
) -> Outcome:
    """Stop one store for ``down_s`` while a fleet streams; count what was stored and how fast it caught up."""
    database_url = env["DATABASE_URL"]
    robots = [robot for robot, _ in pairs]
    fleet_dir.mkdir()
    fleet = Fleet(cloud.ws_url, pairs, fleet_dir)
    try:
        fleet.start()
        fleet.wait_connected(timeout=60)
        time.sleep(stream_s)
        stop()
        time.sleep(down_s)
        start()
        back_at = time.monotonic()
        made_before = fleet.sent()
        try:
            wait_until(
                lambda: count_stored(database_url, robots).distinct >= made_before,
                "every point made before the store's return stored",
                120,
                interval=0.2,
            )
            recover_s: float | None = round(time.monotonic() - back_at, 2)
        except TimeoutError:
            recover_s = None
        time.sleep(stream_s / 2)
        fleet.quiesce()
        fleet.wait_delivered(timeout=120)
        sent = fleet.sent()
        stored = count_stored(database_url, robots)
    finally:
        fleet.stop()
    lost = max(0, sent - stored.distinct)
    alive = cloud.process is not None and cloud.process.poll() is None
    passed = alive and lost == 0 and stored.duplicated == 0 and recover_s is not None and recover_s <= RECOVER_GOAL_S
    return Outcome(
        scenario=NAME,
        injected=injected,
        sent=sent,
        stored=stored.distinct,
        lost=lost,
        duplicated=stored.duplicated,
        recover_s=recover_s,
        passed=passed,
        detail=f"daphne {'kept running' if alive else 'DIED'}; backlog stored {recover_s} s after the store's return",
    )


if __name__ == "__main__":
    for outcome in run("--full" not in sys.argv):
        print(outcome)
