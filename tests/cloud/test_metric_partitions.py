"""The metric table partitioned by day on real PostgreSQL: the migration keeps rows, retention drops partitions."""

from __future__ import annotations

import re
import time
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime, timedelta

import pytest
from django.db import connection, connections
from django.db.migrations.executor import MigrationExecutor
from django.test import Client
from django.utils import timezone

from monitoring import partitions, services
from monitoring.models import Metric
from robots.services import create_robot

from .apiutil import robot_of, user_with_token

pytestmark = pytest.mark.django_db(transaction=True)

BEFORE = ("monitoring", "0004_ingested_frame")
PARTITIONED = ("monitoring", "0005_metric_partitioned_by_day")
# Where each test leaves the schema, as the rest of the suite expects it.
LATEST = ("monitoring", "0006_metric_robot_locked_not_constrained")


@pytest.fixture
def robot():
    owner, _ = user_with_token("part-owner")
    create_robot("part-bot", owner)
    return "part-bot"


def migrate_to(target: tuple[str, str]) -> None:
    executor = MigrationExecutor(connection)
    executor.migrate([target])


def relkind() -> str:
    with connection.cursor() as cursor:
        cursor.execute("SELECT relkind FROM pg_class WHERE oid = to_regclass('monitoring_metric')")
        return cursor.fetchone()[0]


def rows() -> list[tuple]:
    with connection.cursor() as cursor:
        cursor.execute("SELECT id, robot_id, name, value, labels::text, ts FROM monitoring_metric ORDER BY id")
        return cursor.fetchall()


def test_rows_written_before_partitioning_survive_the_migration(robot):
    now = timezone.now()
    migrate_to(BEFORE)
    try:
        assert relkind() == "r"
        with connection.cursor() as cursor:
            # Today, last week, two years ago (older than retention) and next month: every row must survive.
            for days, value in ((0, 1.5), (7, 2.5), (730, 3.5), (-30, 4.5)):
                cursor.execute(
                    "INSERT INTO monitoring_metric (robot_id, skill, component, name, value, labels, ts)"
                    " VALUES (%s, '', '', 'cpu', %s, '{\"k\": \"v\"}', %s)",
                    [robot, value, now - timedelta(days=days)],
                )
        before = rows()

        migrate_to(PARTITIONED)

        assert relkind() == "p"
        assert rows() == before
        assert partitions.day_of(now) in partitions.partition_days()
        # Ids go on from the old sequence: a new point never reuses one.
        new = Metric.objects.create(robot_id=robot, name="cpu", value=9.0, ts=now)
        assert new.id > max(row[0] for row in before)
    finally:
        migrate_to(LATEST)


def test_migration_back_to_a_plain_table_keeps_rows(robot):
    now = timezone.now()
    Metric.objects.bulk_create(
        [Metric(robot_id=robot, name="cpu", value=i, ts=now - timedelta(days=i)) for i in range(5)]
    )
    before = rows()
    try:
        migrate_to(BEFORE)
        assert relkind() == "r"
        assert rows() == before
        assert Metric.objects.create(robot_id=robot, name="cpu", value=9.0, ts=now).id > before[-1][0]
    finally:
        migrate_to(LATEST)
    assert relkind() == "p"
    assert len(rows()) == 6


def test_a_point_on_a_day_without_partition_is_kept_and_moves_when_its_day_is_created(robot):
    far = datetime(2031, 5, 4, 12, tzinfo=UTC)
    Metric.objects.create(robot_id=robot, name="cpu", value=1.0, ts=far)
    assert partitions.day_of(far) not in partitions.partition_days()

    assert partitions.create_partitions([far.date()]) == [far.date()]

    with connection.cursor() as cursor:
        cursor.execute("SELECT tableoid::regclass::text, value FROM monitoring_metric WHERE ts = %s", [far])
        assert cursor.fetchall() == [(partitions.partition_name(far.date()), 1.0)]
    assert partitions.create_partitions([far.date()]) == []


def test_partitions_exist_ahead_of_today():
    today = partitions.day_of(timezone.now())
    partitions.ensure_partitions()
    days = set(partitions.partition_days())
    assert {today + timedelta(days=n) for n in range(-1, 8)} <= days


def test_prune_drops_expired_partitions_whole_and_deletes_rows_of_the_partly_expired_day(robot):
    now = datetime(2026, 11, 20, 12, tzinfo=UTC)
    days = partitions.days_between(date_of(now - timedelta(days=6)), date_of(now))
    partitions.create_partitions(days)
    # Four points a day at 00:00, 06:00, 12:00 and 18:00 for a week.
    points = [
        Metric(robot_id=robot, name="cpu", value=1.0, ts=partitions.day_start(day) + timedelta(hours=h))
        for day in days
        for h in (0, 6, 12, 18)
    ]
    Metric.objects.bulk_create(points)
    cutoff = now - timedelta(days=3, hours=3)  # 17 Nov 09:00: 14..16 Nov go whole, two rows of the 17th

    deleted = services.prune_metrics(timedelta(days=3, hours=3), now=now)

    assert deleted == 3 * 4 + 2
    remaining = set(partitions.partition_days())
    assert not remaining & set(days[:3])
    assert set(days[3:]) <= remaining
    assert Metric.objects.filter(ts__lt=cutoff).count() == 0
    assert Metric.objects.count() == len(points) - deleted


def date_of(ts: datetime):
    return partitions.day_of(ts)


def test_a_time_range_query_reads_only_its_partitions(robot):
    now = timezone.now()
    partitions.ensure_partitions(now)
    with connection.cursor() as cursor:
        cursor.execute(
            "EXPLAIN SELECT avg(value) FROM monitoring_metric WHERE robot_id = ANY(%s) AND ts >= %s AND ts < %s",
            [[robot], now - timedelta(minutes=30), now],
        )
        plan = "\n".join(row[0] for row in cursor.fetchall())
    # Partition tables only: past midnight the plan also names their indexes and aliases (monitoring_metric_1).
    scanned = set(re.findall(r"\bmonitoring_metric_p\d{8}\b", plan))
    assert scanned
    assert scanned <= {partitions.partition_name(partitions.day_of(now - timedelta(minutes=30 * n))) for n in (0, 1)}


def test_a_query_past_the_statement_timeout_fails_clearly_and_fast(monkeypatch):
    user, key = user_with_token("slow-query")
    robot_of(user, "slow-bot", with_skill=False)
    now = timezone.now()
    with connection.cursor() as cursor:
        cursor.execute(
            "INSERT INTO monitoring_metric (robot_id, skill, component, name, value, labels, ts)"
            " SELECT 'slow-bot', '', '', 'm' || (g %% 50), g, '{}', %s - g * interval '10 ms'"
            " FROM generate_series(1, 200000) g",
            [now],
        )
    # Through the real view in this process, so the lowered deadline applies to it.
    http = Client(HTTP_AUTHORIZATION=f"Token {key}")
    body = {"since": (now - timedelta(hours=1)).isoformat(), "until": now.isoformat(), "bucket": 1}
    monkeypatch.setattr(services, "QUERY_TIMEOUT_MS", 1)
    started = time.monotonic()
    answer = http.post("/api/database/query", body, content_type="application/json")
    assert answer.status_code == 503
    assert "took too long" in answer.json()["detail"]
    assert time.monotonic() - started < 10
    monkeypatch.setattr(services, "QUERY_TIMEOUT_MS", 5000)
    answer = http.post("/api/database/query", body, content_type="application/json")
    assert answer.status_code == 200
    assert sum(row["points"] for row in answer.json()["results"]) > 0


def test_processes_creating_and_dropping_the_same_partitions_at_once_all_succeed(robot):
    days = partitions.days_between(datetime(2032, 1, 1, tzinfo=UTC).date(), datetime(2032, 1, 6, tzinfo=UTC).date())
    cutoff = datetime(2032, 2, 1, tzinfo=UTC)

    def maintain(work):
        try:
            return work()
        finally:
            connections.close_all()

    with ThreadPoolExecutor(4) as pool:
        created = list(pool.map(maintain, [lambda: partitions.create_partitions(days)] * 4))
    assert sorted(day for batch in created for day in batch) == days
    Metric.objects.create(robot_id=robot, name="cpu", value=1.0, ts=partitions.day_start(days[2]) + timedelta(hours=1))
    with ThreadPoolExecutor(4) as pool:
        dropped = list(pool.map(maintain, [lambda: partitions.drop_expired_partitions(cutoff)] * 4))
    assert sum(dropped) == 1
    assert not set(days) & set(partitions.partition_days())
