"""/api/database/query and /api/events: aggregations checked exactly against known rows, filters, pages."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from typing import Any

import pytest

from monitoring.models import Event, Metric

from .apiutil import client, robot_of, user_with_token

pytestmark = pytest.mark.django_db(transaction=True)

T0 = datetime(2026, 1, 1, tzinfo=UTC)
# The detector's latency on alice-bot: three points in the first minute, two in the second.
LATENCY = [(0, 1.0), (10, 3.0), (20, 2.0), (70, 10.0), (80, 4.0)]
RANGE = {"since": T0.isoformat(), "until": (T0 + timedelta(minutes=2)).isoformat()}


def at(seconds: float) -> datetime:
    return T0 + timedelta(seconds=seconds)


def iso(seconds: float) -> str:
    return at(seconds).isoformat().replace("+00:00", "Z")


@pytest.fixture
def fleet(daphne_server) -> dict[str, Any]:
    """Alice owns alice-bot and alice-two, Bob owns bob-bot; known metric points and a clean event log."""
    alice, alice_key = user_with_token("alice")
    bob, bob_key = user_with_token("bob")
    _, staff_key = user_with_token("ops", staff=True)
    for owner, robot_id in ((alice, "alice-bot"), (alice, "alice-two"), (bob, "bob-bot")):
        robot_of(owner, robot_id, with_skill=False)
    points = [
        Metric(robot_id="alice-bot", skill="people-detection", component="detector", name="latency", value=v, ts=at(s))
        for s, v in LATENCY
    ]
    points += [
        Metric(robot_id="alice-bot", name="cpu", value=0.25, ts=at(5)),
        Metric(robot_id="alice-bot", name="cpu", value=0.75, ts=at(65)),
        Metric(robot_id="alice-two", name="cpu", value=0.5, ts=at(30)),
        Metric(robot_id="bob-bot", name="cpu", value=0.9, ts=at(30)),
        # Just outside the range on both sides.
        Metric(robot_id="alice-bot", name="cpu", value=100.0, ts=at(-1)),
        Metric(robot_id="alice-bot", name="cpu", value=100.0, ts=at(120)),
    ]
    Metric.objects.bulk_create(points)
    Event.objects.all().delete()
    return {"alice": alice_key, "bob": bob_key, "staff": staff_key, "server": daphne_server}


def query(fleet: dict[str, Any], body: dict[str, Any], who: str = "alice") -> Any:
    with client(fleet["server"], fleet[who]) as http:
        return http.post("/api/database/query", json=body)


def rows(fleet: dict[str, Any], body: dict[str, Any], who: str = "alice") -> list[dict[str, Any]]:
    response = query(fleet, {**RANGE, **body}, who)
    assert response.status_code == 200, response.text
    assert response.json()["kind"] == "metrics"
    return response.json()["results"]


# --------------------------------------------------------------------------- metrics


@pytest.mark.parametrize(
    ("aggregate", "first_minute", "second_minute", "whole"),
    [
        ("avg", 2.0, 7.0, 4.0),
        ("min", 1.0, 4.0, 1.0),
        ("max", 3.0, 10.0, 10.0),
        ("last", 2.0, 4.0, 4.0),
        ("count", 3.0, 2.0, 5.0),
    ],
)
def test_each_aggregate_matches_the_stored_points_per_bucket_and_over_the_range(
    fleet, aggregate, first_minute, second_minute, whole
):
    per_minute = rows(fleet, {"names": ["latency"], "aggregate": aggregate, "bucket": 60})
    assert [(r["bucket"], r["value"], r["points"]) for r in per_minute] == [
        (iso(60), second_minute, 2),
        (iso(0), first_minute, 3),
    ]
    assert {(r["robot"], r["skill"], r["component"], r["name"]) for r in per_minute} == {
        ("alice-bot", "people-detection", "detector", "latency")
    }
    [over_range] = rows(fleet, {"names": ["latency"], "aggregate": aggregate})
    # Without buckets a series is one row, stamped with its first point.
    assert (over_range["bucket"], over_range["value"], over_range["points"]) == (iso(0), whole, 5)


def test_the_range_includes_since_and_excludes_until(fleet):
    [cpu] = rows(fleet, {"names": ["cpu"], "robots": ["alice-bot"], "aggregate": "count"})
    assert cpu["value"] == 2.0
    [cpu] = rows(fleet, {"names": ["cpu"], "robots": ["alice-bot"], "since": iso(-1), "until": iso(65)})
    assert (cpu["bucket"], cpu["value"], cpu["points"]) == (iso(-1), 50.125, 2)


def test_metrics_are_filtered_by_robot_name_skill_and_component(fleet):
    everything = rows(fleet, {})
    assert {(r["robot"], r["name"]) for r in everything} == {
        ("alice-bot", "latency"),
        ("alice-bot", "cpu"),
        ("alice-two", "cpu"),
    }
    assert {r["robot"] for r in rows(fleet, {"robots": ["alice-two"]})} == {"alice-two"}
    assert {r["name"] for r in rows(fleet, {"names": ["cpu"]})} == {"cpu"}
    assert {r["name"] for r in rows(fleet, {"skill": "people-detection"})} == {"latency"}
    assert {r["name"] for r in rows(fleet, {"component": "detector"})} == {"latency"}
    assert rows(fleet, {"component": "sampler"}) == []
    assert rows(fleet, {"names": ["no-such-metric"]}) == []


def test_rows_come_newest_bucket_first_and_stop_at_the_limit(fleet):
    per_minute = rows(fleet, {"bucket": 60})
    buckets = [r["bucket"] for r in per_minute]
    assert buckets == sorted(buckets, reverse=True)
    assert len(per_minute) == 5
    assert rows(fleet, {"bucket": 60, "limit": 2}) == per_minute[:2]


def test_staff_query_every_robot_and_others_only_their_own(fleet):
    assert {r["robot"] for r in rows(fleet, {"names": ["cpu"]}, "staff")} == {"alice-bot", "alice-two", "bob-bot"}
    [bobs] = rows(fleet, {}, "bob")
    assert (bobs["robot"], bobs["value"]) == ("bob-bot", 0.9)


def test_the_default_range_is_the_last_hour(fleet):
    response = query(fleet, {"names": ["latency"]})
    assert response.status_code == 200
    assert response.json()["results"] == []


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"since": iso(60), "until": iso(0)}, "since"),
        ({"since": iso(0), "until": iso(0)}, "since"),
        ({"since": iso(0), "until": (T0 + timedelta(days=400)).isoformat()}, "since"),
        ({"since": "yesterday"}, "since"),
        ({"aggregate": "median"}, "aggregate"),
        ({"bucket": 0}, "bucket"),
        ({"bucket": 86_401}, "bucket"),
        ({"limit": 0}, "limit"),
        ({"limit": 10_001}, "limit"),
        ({"names": "cpu"}, "names"),
        ({"robots": ["no-such-bot"]}, "robots"),
        ({"robots": ["bob-bot"]}, "robots"),
        ({"robots": ["Not A Slug"]}, "robots"),
        ({"kind": "logs"}, "kind"),
        ({"level": "loud", "kind": "events"}, "level"),
    ],
)
def test_an_invalid_query_is_refused_naming_the_field(fleet, body, field):
    response = query(fleet, body)
    assert response.status_code == 400, response.text
    assert field in response.json()


def test_an_average_past_the_largest_float_is_refused_rather_than_a_crash(fleet):
    Metric.objects.bulk_create(
        Metric(robot_id="alice-bot", name="huge", value=1.5e308, ts=at(seconds)) for seconds in (1, 2)
    )
    response = query(fleet, {**RANGE, "names": ["huge"], "aggregate": "avg"})
    assert response.status_code == 400, response.text
    assert "aggregate" in response.json()
    [biggest] = rows(fleet, {"names": ["huge"], "aggregate": "max"})
    assert biggest["value"] == 1.5e308


def test_another_users_robot_is_refused_like_a_missing_one(fleet):
    theirs = query(fleet, {"robots": ["bob-bot"]}).json()
    missing = query(fleet, {"robots": ["nope-bot"]}).json()
    assert theirs == {"robots": ["No robot 'bob-bot'."]}
    assert missing == {"robots": ["No robot 'nope-bot'."]}


# --------------------------------------------------------------------------- events


@pytest.fixture
def log(fleet) -> dict[str, Any]:
    """Six events of alice's robots at known times, one of Bob's and one fleet-wide."""
    Event.objects.bulk_create(
        [
            Event(ts=at(0), robot_id="alice-bot", level="debug", kind="heartbeat", message="beat"),
            Event(
                ts=at(10),
                robot_id="alice-bot",
                level="info",
                kind="skill_status",
                skill="people-detection",
                message="skill running",
            ),
            Event(
                ts=at(20),
                robot_id="alice-bot",
                level="warning",
                kind="component_status",
                skill="people-detection",
                component="detector",
                message="detector slow",
            ),
            Event(
                ts=at(30),
                robot_id="alice-bot",
                level="error",
                kind="component_status",
                skill="people-detection",
                component="sampler",
                message="sampler failed",
            ),
            Event(ts=at(40), robot_id="alice-two", level="info", kind="connection_established", message="up"),
            Event(ts=at(50), robot_id="alice-two", level="error", kind="connection_lost", message="down"),
            Event(ts=at(25), robot_id="bob-bot", level="error", kind="connection_lost", message="bob down"),
            Event(ts=at(35), robot_id=None, level="info", kind="robot_deleted", message="fleet-wide"),
        ]
    )
    return fleet


def events(log: dict[str, Any], params: str = "", who: str = "alice") -> dict[str, Any]:
    with client(log["server"], log[who]) as http:
        response = http.get("/api/events" + params)
    assert response.status_code == 200, response.text
    return response.json()


def messages(page: dict[str, Any]) -> list[str]:
    return [event["message"] for event in page["results"]]


def test_the_event_log_lists_the_callers_robots_newest_first(log):
    page = events(log)
    assert page["count"] == 6
    assert messages(page) == ["down", "up", "sampler failed", "detector slow", "skill running", "beat"]
    first = page["results"][0]
    assert set(first) == {"id", "ts", "level", "source", "kind", "robot", "skill", "component", "message", "data"}
    assert (first["robot"], first["ts"]) == ("alice-two", iso(50))


def test_staff_see_every_event_including_fleet_wide_ones(log):
    page = events(log, who="staff")
    assert page["count"] == 8
    assert "fleet-wide" in messages(page) and "bob down" in messages(page)
    assert messages(events(log, who="bob")) == ["bob down"]


@pytest.mark.parametrize(
    ("params", "expected"),
    [
        ("?robot=alice-two", ["down", "up"]),
        ("?skill=people-detection", ["sampler failed", "detector slow", "skill running"]),
        ("?component=detector", ["detector slow"]),
        ("?kind=component_status", ["sampler failed", "detector slow"]),
        ("?level=warning", ["down", "sampler failed", "detector slow"]),
        ("?level=error", ["down", "sampler failed"]),
        (f"?since={iso(20)}", ["down", "up", "sampler failed", "detector slow"]),
        (f"?until={iso(20)}", ["skill running", "beat"]),
        (f"?since={iso(10)}&until={iso(40)}&level=info", ["sampler failed", "detector slow", "skill running"]),
        ("?robot=bob-bot", []),
    ],
)
def test_the_event_log_is_filtered(log, params, expected):
    assert messages(events(log, params)) == expected


def test_the_event_log_is_paginated(log):
    first = events(log, "?limit=4")
    assert first["count"] == 6 and len(first["results"]) == 4 and first["previous"] is None
    assert "offset=4" in first["next"]
    second = events(log, "?limit=4&offset=4")
    assert second["next"] is None
    assert messages(first) + messages(second) == messages(events(log))


def test_a_page_is_at_most_a_thousand_events_whatever_the_limit_asked(log):
    Event.objects.bulk_create(Event(ts=at(60), robot_id="alice-bot", message="bulk") for _ in range(1001))
    page = events(log, "?limit=100000000000000000000")
    assert page["count"] == 1007 and len(page["results"]) == 1000
    assert events(log, "?offset=100000000000000000000")["results"] == []


@pytest.mark.parametrize("params", ["?level=loud", "?since=yesterday", "?robot=Not%20A%20Slug", "?kind=a%00b"])
def test_an_invalid_event_filter_is_a_bad_request(log, params):
    with client(log["server"], log["alice"]) as http:
        assert http.get("/api/events" + params).status_code == 400


def test_events_are_queried_with_the_same_filters_through_the_database_query(log):
    response = query(log, {**RANGE, "kind": "events", "robots": ["alice-bot"], "level": "warning", "limit": 1})
    assert response.status_code == 200
    assert response.json()["kind"] == "events"
    assert [e["message"] for e in response.json()["results"]] == ["sampler failed"]
    everything = query(log, {**RANGE, "kind": "events"}).json()["results"]
    assert len(everything) == 6
    outside = query(log, {"kind": "events", "since": iso(60), "until": iso(120)}).json()["results"]
    assert outside == []
