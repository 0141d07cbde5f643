"""GET /api/robot/<id>/logs and its download: filters by level, text, regex and time, cursor pages, 404 and 400."""

from __future__ import annotations

import time
from typing import Any

import pytest

from logs.services import store_lines
from tests.cloud.apiutil import client, robot_of, user_with_token

pytestmark = pytest.mark.django_db(transaction=True)

SKILL = "people-detection"
T0 = time.time() - 600  # ten minutes ago: inside today's (or yesterday's) partition


def line(seq: int, text: str, level: str | None = None, *, stream: str = "stdout", at: float | None = None) -> dict:
    return {"seq": seq, "ts": T0 + seq if at is None else at, "stream": stream, "level": level, "text": text}


@pytest.fixture
def logs_fleet(daphne_server) -> dict[str, Any]:
    """Alice's robot lg-alice with known lines of two components; Bob's robot lg-bob with one."""
    alice, alice_key = user_with_token("lg-alice-user")
    bob, bob_key = user_with_token("lg-bob-user")
    robot_of(alice, "lg-alice")
    robot_of(bob, "lg-bob")
    detector = [
        line(1, "starting detector", "info"),
        line(2, "model loaded in 1.2 s"),
        line(3, "frame 17 slow: 250 ms", "warning"),
        line(4, "CUDA out of memory", "error"),
        line(5, "debugging frame 18", "debug"),
        line(6, "fatal: giving up", "critical", stream="stderr"),
    ]
    assert store_lines("lg-alice", SKILL, "detector", "robot", detector, dropped=7) == 6
    assert store_lines("lg-alice", SKILL, "sampler", "cloud", [line(1, "sampled 100% of points_x")]) == 1
    store_lines("lg-bob", SKILL, "detector", "robot", [line(1, "bob's secret line")])
    return {"alice": alice_key, "bob": bob_key, "server": daphne_server}


def get(fleet: dict, path: str, token: str | None = None, **params: Any):
    with client(fleet["server"], token or fleet["alice"]) as http:
        return http.get(path, params=params)


def texts(response) -> list[str]:
    assert response.status_code == 200, response.text
    return [row["text"] for row in response.json()["results"]]


def test_lines_come_newest_first_with_every_field(logs_fleet):
    body = get(logs_fleet, "/api/robot/lg-alice/logs", component="detector").json()
    assert [row["seq"] for row in body["results"]] == [6, 5, 4, 3, 2, 1]
    assert body["results"][0] == {
        "skill": SKILL,
        "component": "detector",
        "location": "robot",
        "seq": 6,
        "ts": body["results"][0]["ts"],
        "stream": "stderr",
        "level": "critical",
        "text": "fatal: giving up",
    }
    assert body["results"][0]["ts"].endswith("Z") or "+00:00" in body["results"][0]["ts"]
    assert body["next"] is None
    assert body["dropped"] == 7


def test_level_is_a_minimum_and_a_line_without_one_counts_as_info(logs_fleet):
    path = "/api/robot/lg-alice/logs"
    assert texts(get(logs_fleet, path, component="detector", level="warning")) == [
        "fatal: giving up",
        "CUDA out of memory",
        "frame 17 slow: 250 ms",
    ]
    info = texts(get(logs_fleet, path, component="detector", level="info", order="asc"))
    assert info == [
        "starting detector",
        "model loaded in 1.2 s",
        "frame 17 slow: 250 ms",
        "CUDA out of memory",
        "fatal: giving up",
    ]
    assert len(texts(get(logs_fleet, path, component="detector", level="debug"))) == 6


def test_text_is_a_case_insensitive_substring_and_wildcards_are_literal(logs_fleet):
    path = "/api/robot/lg-alice/logs"
    assert texts(get(logs_fleet, path, q="cuda OUT")) == ["CUDA out of memory"]
    assert texts(get(logs_fleet, path, q="100%")) == ["sampled 100% of points_x"]
    assert texts(get(logs_fleet, path, q="points_x")) == ["sampled 100% of points_x"]
    assert texts(get(logs_fleet, path, q="1_0")) == []
    assert texts(get(logs_fleet, path, q="secret")) == []  # Bob's robot's line


def test_a_regular_expression_filters_and_a_bad_one_is_a_400_naming_q(logs_fleet):
    path = "/api/robot/lg-alice/logs"
    assert texts(get(logs_fleet, path, q=r"frame \d+ slow", regex="true")) == ["frame 17 slow: 250 ms"]
    refused = get(logs_fleet, path, q="(unclosed", regex="true")
    assert refused.status_code == 400
    assert list(refused.json()) == ["q"]


def test_time_range_location_and_skill_filters(logs_fleet):
    path = "/api/robot/lg-alice/logs"
    assert texts(get(logs_fleet, path, since=str(T0 + 3), until=str(T0 + 5), order="asc")) == [
        "frame 17 slow: 250 ms",
        "CUDA out of memory",
    ]
    iso = time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(T0 + 5)) + "Z"
    assert texts(get(logs_fleet, path, component="detector", since=iso)) == ["fatal: giving up", "debugging frame 18"]
    assert texts(get(logs_fleet, path, location="cloud")) == ["sampled 100% of points_x"]
    assert texts(get(logs_fleet, path, skill="other-skill")) == []


def test_cursor_pages_walk_every_line_once(logs_fleet):
    seen, params = [], {"limit": 2, "component": "detector"}
    with client(logs_fleet["server"], logs_fleet["alice"]) as http:
        url = "/api/robot/lg-alice/logs"
        while url:
            body = http.get(url, params=params).json()
            params = None  # the next link carries them
            seen.extend(row["seq"] for row in body["results"])
            assert len(body["results"]) <= 2
            url = body["next"]
    assert seen == [6, 5, 4, 3, 2, 1]


def test_another_users_robot_and_an_unknown_one_are_404(logs_fleet):
    assert get(logs_fleet, "/api/robot/lg-bob/logs").status_code == 404
    assert get(logs_fleet, "/api/robot/lg-bob/logs/download").status_code == 404
    assert get(logs_fleet, "/api/robot/lg-nobody/logs").status_code == 404
    assert texts(get(logs_fleet, "/api/robot/lg-bob/logs", token=logs_fleet["bob"])) == ["bob's secret line"]


@pytest.mark.parametrize(
    ("param", "value"),
    [
        ("level", "loud"),
        ("location", "moon"),
        ("since", "yesterday-ish"),
        ("limit", "0"),
        ("limit", "1001"),
        ("order", "sideways"),
        ("cursor", "not-a-cursor"),
        ("skill", "no spaces!"),
    ],
)
def test_a_bad_parameter_is_a_400_naming_it(logs_fleet, param, value):
    refused = get(logs_fleet, "/api/robot/lg-alice/logs", **{param: value})
    assert refused.status_code == 400, refused.text
    assert list(refused.json()) == [param]


def test_since_after_until_is_refused(logs_fleet):
    refused = get(logs_fleet, "/api/robot/lg-alice/logs", since=str(T0 + 10), until=str(T0))
    assert refused.status_code == 400
    assert list(refused.json()) == ["since"]


def test_the_download_is_the_filtered_lines_oldest_first_as_text(logs_fleet):
    response = get(logs_fleet, "/api/robot/lg-alice/logs/download", component="detector", level="error")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    assert "attachment" in response.headers["content-disposition"]
    rows = response.text.splitlines()
    assert len(rows) == 2
    assert rows[0].endswith(" robot stdout ERROR people-detection/detector: CUDA out of memory")
    assert rows[1].endswith(" robot stderr CRITICAL people-detection/detector: fatal: giving up")
    assert rows[0][:24].endswith("Z") and rows[0][19] == "."
