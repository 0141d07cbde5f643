"""Kill the cloud's processes with `kill -9`: daphne while robots stream, the Celery worker mid-task, beat.

daphne: a fleet of real agents (`--simulate`) streams metrics; daphne is killed, stays down, and is
started again on the same port. Every point a robot made must be in PostgreSQL exactly once, and
every robot connected again soon after daphne's return (`reconnect_s`).

Celery worker: a retention task (`monitoring.tasks.prune_metrics`) is held mid-way by a table
lock, the worker and its pool are killed, and a new worker must finish the task: it is
acknowledged late (`acks_late`), so Redis keeps it and hands it out again once its visibility
timeout passed (short here, by `CELERY_VISIBILITY_TIMEOUT_S`, to keep the scenario brief).

beat: the reconciler's periodic round runs, beat is killed and started again; the rounds resume.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import time
import uuid

import psycopg

from benchmarks.chaos import Outcome
from benchmarks.chaos.rig import BIN, Beat, Cloud, Fleet, count_stored, create_robots, wait_until

NAME = "processes"
INJECTS = "kill -9 of daphne (robots streaming), of the Celery worker mid-task, and of beat"
# Every robot back within this long of daphne's return (issue 20's goal).
RECONNECT_GOAL_S = 5.0


def run(quick: bool) -> list[Outcome]:
    """Play the three kills; one outcome each."""
    visibility = 3.0 if quick else 10.0
    cloud = Cloud(
        NAME,
        concurrency=1,
        CELERY_VISIBILITY_TIMEOUT_S=str(visibility),
        CELERY_UNACKED_RESTORE_S="1",
        BRIDGEOS_CLOUD_RECONCILE_S="1",
    )
    # Its start-up overlaps the daphne case; the worker case needs it only later.
    cloud.worker.start(wait=False)
    try:
        return [
            daphne_killed(cloud, robots=10 if quick else 50, down_s=3.0 if quick else 12.0, quick=quick),
            worker_killed(cloud, visibility),
            beat_killed(cloud),
        ]
    finally:
        cloud.stop()
        shutil.rmtree(cloud.dir, ignore_errors=True)


def daphne_killed(cloud: Cloud, *, robots: int, down_s: float, quick: bool) -> Outcome:
    """kill -9 daphne while the fleet streams; restart it on the same port; count what was stored."""
    injected = f"daphne kill -9, down {down_s:.0f} s, {robots} robots streaming"
    env, daphne = cloud.env, cloud.server
    prefix = f"chaos-dk-{uuid.uuid4().hex[:6]}"
    pairs = create_robots(env, prefix, robots)
    fleet = Fleet(daphne.ws_url, pairs, cloud.dir)
    try:
        daphne.start()
        fleet.start()
        fleet.wait_connected(timeout=60)
        time.sleep(2.0 if quick else 10.0)
        killed_at = time.time()
        daphne.kill()
        time.sleep(down_s)
        back_at = daphne.start()
        last_connected = fleet.wait_connected(since=killed_at, timeout=120)
        reconnect_s = round(last_connected - back_at, 2)
        time.sleep(1.0 if quick else 10.0)
        fleet.quiesce()
        fleet.wait_delivered(timeout=120)
        sent = fleet.sent()
        stored = count_stored(env["DATABASE_URL"], [robot for robot, _ in pairs])
    finally:
        fleet.stop()
        daphne.stop()
    lost = max(0, sent - stored.distinct)
    passed = lost == 0 and stored.duplicated == 0 and stored.distinct == sent and reconnect_s <= RECONNECT_GOAL_S
    return Outcome(
        scenario=NAME,
        injected=injected,
        sent=sent,
        stored=stored.distinct,
        lost=lost,
        duplicated=stored.duplicated,
        recover_s=reconnect_s,
        passed=passed,
        detail=f"every robot reconnected {reconnect_s} s after daphne was back (goal {RECONNECT_GOAL_S} s)",
        figures={"reconnect_s": reconnect_s},
    )


def _old_points(database_url: str, robot: str, count: int) -> None:
    """Store ``count`` points two days old for one robot: work for the retention task."""
    with psycopg.connect(database_url, autocommit=True) as conn:
        conn.execute(
            "INSERT INTO monitoring_metric (robot_id, skill, component, name, value, labels, ts) "
            "SELECT %s, '', '', 'cpu', n, '{}', now() - interval '2 days' - n * interval '1 second' "
            "FROM generate_series(1, %s) n",
            [robot, count],
        )


def _count_old(database_url: str, robot: str) -> int:
    with psycopg.connect(database_url, autocommit=True) as conn:
        row = conn.execute("SELECT count(*) FROM monitoring_metric WHERE robot_id = %s", [robot]).fetchone()
    return int(row[0]) if row else 0


def _waiting_delete(database_url: str) -> bool:
    """Whether the retention task waits for a lock on the metric table (it is mid-way).

    With day partitions the task may wait in its DELETE, in a partition's DROP or LOCK, or in
    creating the days ahead; ingest's COPY and INSERT wait there too and are not the task.
    """
    with psycopg.connect(database_url, autocommit=True) as conn:
        row = conn.execute(
            "SELECT count(*) FROM pg_stat_activity WHERE wait_event_type = 'Lock' "
            "AND query ILIKE '%%monitoring_metric%%' AND query NOT ILIKE 'COPY%%' AND query NOT ILIKE 'INSERT%%' "
            "AND query NOT ILIKE 'LOCK TABLE monitoring_metric IN SHARE MODE'"
        ).fetchone()
    return bool(row and row[0])


def worker_killed(cloud: Cloud, visibility: float) -> Outcome:
    """kill -9 the worker (and its pool) while a retention task is mid-way; a new worker must finish it."""
    env, worker = cloud.env, cloud.worker
    injected = "Celery worker kill -9 mid-task (prune_metrics blocked on a table lock)"
    database_url = env["DATABASE_URL"]
    prefix = f"chaos-wk-{uuid.uuid4().hex[:6]}"
    robot = create_robots(env, prefix, 1)[0][0]
    points = 2000
    _old_points(database_url, robot, points)
    holder = psycopg.connect(database_url)
    try:
        # The task's DELETE waits behind this lock: the worker is killed while it runs the task.
        holder.execute("LOCK TABLE monitoring_metric IN SHARE MODE")
        worker.wait_ready()
        subprocess.run(
            [
                *(str(BIN / "celery"), "-A", "bridgeos_cloud", "call", "monitoring.tasks.prune_metrics"),
                *("--args", "[86400]", "--queue", env["CELERY_TASK_DEFAULT_QUEUE"]),
            ],
            env={**os.environ, **env},
            check=True,
            capture_output=True,
            cwd=str(cloud.dir),
        )
        wait_until(lambda: _waiting_delete(database_url), "the task waiting on the metric table", 30)
        worker.kill()
        holder.rollback()
        left_after_kill = _count_old(database_url, robot)
        restarted_at = time.monotonic()
        worker.start()
        try:
            wait_until(lambda: _count_old(database_url, robot) == 0, "the task done", visibility + 60)
            recover_s = round(time.monotonic() - restarted_at, 2)
            wait_until(lambda: worker.succeeded("monitoring.tasks.prune_metrics"), "its success", 10)
        except TimeoutError:
            recover_s = None
        done = worker.succeeded("monitoring.tasks.prune_metrics")
    finally:
        holder.close()
    left = _count_old(database_url, robot)
    passed = left_after_kill == points and left == 0 and done == 1
    return Outcome(
        scenario=NAME,
        injected=injected,
        sent=points,
        stored=points - left,
        recover_s=recover_s,
        passed=passed,
        detail=(
            f"{left_after_kill} points still there after the kill, {left} after the new worker; the task succeeded "
            f"{done} time(s); redelivered after the visibility timeout ({visibility:.0f} s here)"
        ),
    )


def beat_killed(cloud: Cloud) -> Outcome:
    """kill -9 beat while the reconciler's round runs every second; restarted, the rounds resume."""
    injected = "Celery beat kill -9 (reconcile every 1 s)"
    task = "skills.tasks.reconcile_cloud"
    worker = cloud.worker
    beat = Beat(cloud.env, cloud.dir)
    try:
        if worker.process is None or worker.process.poll() is not None:
            worker.start()
        beat.start()
        wait_until(lambda: worker.succeeded(task) >= 2, "two reconcile rounds", 30)
        beat.kill()
        time.sleep(1.0)
        before = worker.succeeded(task)
        restarted_at = time.monotonic()
        beat.start()
        try:
            wait_until(lambda: worker.succeeded(task) > before, "a round after beat's restart", 30)
            recover_s = round(time.monotonic() - restarted_at, 2)
            wait_until(lambda: worker.succeeded(task) >= before + 3, "three rounds after it", 30)
        except TimeoutError:
            recover_s = None
        after = worker.succeeded(task)
    finally:
        beat.stop()
    passed = recover_s is not None and after >= before + 3
    return Outcome(
        scenario=NAME,
        injected=injected,
        sent=after,
        stored=after,
        recover_s=recover_s,
        passed=passed,
        detail=f"{before} rounds before the kill, {after - before} after the restart",
    )


if __name__ == "__main__":
    for outcome in run("--full" not in sys.argv):
        print(outcome)
