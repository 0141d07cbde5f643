"""The log table on real PostgreSQL: partitioned by day, a trigram index on text, retention by dropping days."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest
from django.db import connection
from django.utils import timezone

from logs import partitions, services
from logs.models import ComponentLog
from tests.conftest import wait_until

pytestmark = pytest.mark.django_db(transaction=True)


def line(seq: int, ts: datetime, text: str = "x") -> dict:
    return {"seq": seq, "ts": ts.timestamp(), "stream": "stdout", "text": text}


def test_the_table_is_partitioned_with_days_ahead_and_its_text_has_a_trigram_index():
    assert partitions.is_partitioned()
    today = partitions.day_of(timezone.now())
    partitions.ensure_partitions()
    assert {today + timedelta(days=n) for n in range(-1, partitions.AHEAD_DAYS + 1)} <= set(partitions.partition_days())
    with connection.cursor() as cursor:
        cursor.execute("SELECT indexdef FROM pg_indexes WHERE tablename = 'logs_componentlog'")
        definitions = " ".join(row[0] for row in cursor.fetchall())
    assert "gin_trgm_ops" in definitions


def test_a_line_on_a_day_without_partition_is_kept_and_moves_when_its_day_is_created():
    far = datetime(2031, 5, 4, 12, tzinfo=UTC)
    assert services.store_lines("lp-bot", "sk", "cam", "robot", [line(1, far)]) == 1
    assert services.store_lines("lp-bot", "sk", "cam", "robot", [line(1, far)]) == 0  # the key is unique there too
    assert partitions.create_partitions([far.date()]) == [far.date()]
    with connection.cursor() as cursor:
        cursor.execute("SELECT tableoid::regclass::text FROM logs_componentlog WHERE robot_id = 'lp-bot'")
        assert cursor.fetchall() == [(partitions.partition_name(far.date()),)]
    assert services.store_lines("lp-bot", "sk", "cam", "robot", [line(1, far)]) == 0


def test_prune_drops_expired_days_whole_and_deletes_the_lines_of_the_partly_expired_day():
    now = datetime(2026, 11, 20, 12, tzinfo=UTC)
    days = partitions.days_between(partitions.day_of(now - timedelta(days=6)), partitions.day_of(now))
    partitions.create_partitions(days)
    moments = [partitions.day_start(day) + timedelta(hours=h) for day in days for h in (0, 6, 12, 18)]
    services.store_lines("lp-old", "sk", "cam", "robot", [line(n + 1, ts) for n, ts in enumerate(moments)])
    cutoff = now - timedelta(days=3, hours=3)  # 17 Nov 09:00: 14..16 Nov go whole, two lines of the 17th

    deleted = services.prune_logs(timedelta(days=3, hours=3), now=now)

    assert deleted == 3 * 4 + 2
    assert not set(partitions.partition_days()) & set(days[:3])
    assert ComponentLog.objects.filter(robot_id="lp-old", ts__lt=cutoff).count() == 0
    assert ComponentLog.objects.filter(robot_id="lp-old").count() == len(moments) - deleted


def test_a_deleted_robots_lines_go_with_it():
    from robots.models import Robot
    from tests.cloud.apiutil import robot_of, user_with_token

    owner, _ = user_with_token("lp-owner")
    robot_of(owner, "lp-gone", with_skill=False)
    services.store_lines("lp-gone", "sk", "cam", "robot", [line(1, timezone.now())], dropped=4)
    Robot.objects.get(id="lp-gone").delete()
    assert not ComponentLog.objects.filter(robot_id="lp-gone").exists()
    assert services.dropped_count("lp-gone", services.LogFilters()) == 0


def test_a_flooded_day_is_analyzed_before_the_next_query():
    now = timezone.now()
    partitions.ensure_partitions(now)
    today = partitions.partition_name(partitions.day_of(now))
    lines = [line(n, now, f"flood {n}") for n in range(1, services.STALE_LINES + 1001)]
    services.store_lines("lp-flood", "sk", "cam", "robot", lines)
    # Statistics counters reach the shared view within a second or so of the inserting transaction's end.
    assert today in wait_until(services.analyze_if_stale, timeout=10, what="the day seen as stale")
    assert services.analyze_if_stale() == []
    rows, _ = services.page_of_lines("lp-flood", services.LogFilters(q="flood 7"), limit=5)
    assert [row.text for row in rows] and all("flood 7" in row.text for row in rows)
