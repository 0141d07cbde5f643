"""Query time of /api/database/query over 10 million metric points (benchmarks/scale.py's `query_10m_points_s`).

The bench database is filled once, server-side (INSERT ... SELECT generate_series, a day
partition at a time) with 10,000,000 points: 100 robots x 10 metrics over 10 days (a point per
series every 86.4 s), and kept between runs (a marker table says it is complete). The query timed
is the slowest common shape: a fleet-wide dashboard view, all 100 robots and all their metrics,
averaged in 5-minute buckets over a whole day (1,000,000 points read, 288,000 groups), POSTed to
a daphne of the benchmark's own, so it goes through the real view, service and statement timeout.

    .venv/bin/python benchmarks/_points.py --quick
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _common import ROOT, Daphne, ensure_postgres_database, log, migrate, percentile

PREFIX = "points-bench-"
OWNER = "points-bench-owner"
ROBOTS = 100
NAMES = 10
DAYS = 10
POINTS_PER_DAY = 1_000_000
MARKER = "bench_points_filled"
BUCKET_S = 300


def fill(database_url: str) -> dict:
    """Fill the database unless a complete fill is there; return an API token and the range to query."""
    from _common import setup_django

    setup_django({"DATABASE_URL": database_url, "REDIS_URL": "", "BRIDGEOS_DATA_DIR": tempfile.mkdtemp()})
    from datetime import timedelta

    from django.contrib.auth import get_user_model
    from django.db import connection
    from django.utils import timezone

    from monitoring import partitions
    from robots.models import Robot, default_robot_config
    from robots.services import issue_api_token
    from teams.services import personal_organization

    with connection.cursor() as cursor:
        cursor.execute(f"CREATE TABLE IF NOT EXISTS {MARKER} (first_day date NOT NULL, points bigint NOT NULL)")
        cursor.execute(f"SELECT first_day, points FROM {MARKER}")
        found = cursor.fetchone()
    User = get_user_model()
    if found is None or found[1] != DAYS * POINTS_PER_DAY:
        started = time.monotonic()
        first_day = partitions.day_of(timezone.now()) - timedelta(days=DAYS)
        Robot.objects.filter(id__startswith=PREFIX).delete()
        User.objects.filter(username=OWNER).delete()
        owner = User.objects.create_user(OWNER)
        config = default_robot_config()
        robots = []
        for i in range(ROBOTS):
            robot = Robot(
                id=f"{PREFIX}{i:03d}",
                owner=owner,
                organization=personal_organization(owner),
                name=f"Points bench robot {i}",
                config=config,
            )
            robot.issue_token()
            robots.append(robot)
        Robot.objects.bulk_create(robots)
        days = partitions.days_between(first_day, first_day + timedelta(days=DAYS - 1))
        partitions.create_partitions(days)
        for n, day in enumerate(days):
            with connection.cursor() as cursor:
                # Server-side: no row crosses the socket. Consecutive points visit every series in turn.
                cursor.execute(
                    "INSERT INTO monitoring_metric (robot_id, skill, component, name, value, labels, ts)"
                    " SELECT %s || lpad((g %% %s)::text, 3, '0'), '', '', 'metric-' || ((g / %s) %% %s),"
                    " random(), '{}', %s + g * (interval '1 second' * 86400.0 / %s)"
                    " FROM generate_series(0, %s - 1) g",
                    [PREFIX, ROBOTS, ROBOTS, NAMES, partitions.day_start(day), POINTS_PER_DAY, POINTS_PER_DAY],
                )
            log(f"points: day {n + 1}/{DAYS} written ({time.monotonic() - started:.0f} s)")
        with connection.cursor() as cursor:
            cursor.execute("ANALYZE monitoring_metric")
            cursor.execute(f"DELETE FROM {MARKER}")
            cursor.execute(f"INSERT INTO {MARKER} VALUES (%s, %s)", [first_day, DAYS * POINTS_PER_DAY])
        log(f"points: {DAYS * POINTS_PER_DAY:,} points written in {time.monotonic() - started:.0f} s")
        found = (first_day, DAYS * POINTS_PER_DAY)
    else:
        log(f"points: the database holds the {found[1]:,} bench points already")
    key, _ = issue_api_token(User.objects.get(username=OWNER))
    last_day = partitions.day_start(found[0] + timedelta(days=DAYS - 1))
    with connection.cursor() as cursor:
        cursor.execute(
            "EXPLAIN SELECT count(*) FROM monitoring_metric WHERE ts >= %s AND ts < %s",
            [last_day, last_day + timedelta(days=1)],
        )
        plan = " ".join(row[0] for row in cursor.fetchall())
    scanned = sorted({word for word in plan.split() if word.startswith("monitoring_metric_")})
    return {
        "token": key,
        "since": last_day.isoformat(),
        "until": (last_day + timedelta(days=1)).isoformat(),
        "partitions_scanned": scanned,
    }


def query_10m_points_s(database_url: str, quick: bool) -> float:
    """Return the seconds a fleet-wide day query over 10M points takes through /api/database/query (median)."""
    import httpx

    ensure_postgres_database(database_url)
    data_dir = tempfile.mkdtemp(prefix="bridgeos-bench-points-")
    env = {"DATABASE_URL": database_url, "REDIS_URL": "", "BRIDGEOS_DATA_DIR": data_dir}
    migrate(env)
    # In a process of its own: the caller may have set Django up against another database.
    filled = subprocess.run(
        [sys.executable, __file__, "--fill", database_url], cwd=ROOT, check=True, stdout=subprocess.PIPE, text=True
    )
    target = json.loads(filled.stdout.strip().splitlines()[-1])
    log(f"points: a day's query reads {', '.join(target['partitions_scanned'])} (partitions pruned to that day)")
    body = {"since": target["since"], "until": target["until"], "bucket": BUCKET_S, "aggregate": "avg"}
    daphne = Daphne(env, Path(data_dir) / "daphne.log")
    try:
        daphne.wait()
        headers = {"Authorization": f"Token {target['token']}"}
        with httpx.Client(base_url=f"http://127.0.0.1:{daphne.port}", headers=headers, timeout=60) as http:
            timings = []
            for attempt in range(2 if quick else 6):
                began = time.perf_counter()
                answer = http.post("/api/database/query", json=body)
                elapsed = time.perf_counter() - began
                if answer.status_code != 200:
                    raise RuntimeError(f"/api/database/query answered {answer.status_code}: {answer.text[:300]}")
                rows = answer.json()["results"]
                log(f"points: query {attempt + 1}: {elapsed:.2f} s, {len(rows)} rows")
                # The first run warms the caches (cold: read from disk); the rest are the figure.
                if attempt:
                    timings.append(elapsed)
    finally:
        daphne.stop()
    return round(percentile(timings, 50), 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--database-url", default="postgres://postgres@127.0.0.1:5432/bridgeos_bench_points")
    parser.add_argument("--fill", metavar="DATABASE_URL", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.fill:
        print(json.dumps(fill(args.fill)), flush=True)
        return
    print(json.dumps({"query_10m_points_s": query_10m_points_s(args.database_url, args.quick)}), flush=True)


if __name__ == "__main__":
    main()
