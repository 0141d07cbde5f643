"""GET /api/robot for big fleets: pages and fields on demand, today's answer without them, clear 400s."""

from __future__ import annotations

from typing import Any

import pytest

from .apiutil import client, robot_of, user_with_token

pytestmark = pytest.mark.django_db(transaction=True)

ROBOTS = [f"fleet-{i:02d}" for i in range(7)]


@pytest.fixture
def fleet(daphne_server) -> dict[str, Any]:
    """Carol owns seven robots (the first two with the sample Skill); Dave owns one."""
    carol, carol_key = user_with_token("carol")
    dave, dave_key = user_with_token("dave")
    for n, robot_id in enumerate(ROBOTS):
        robot_of(carol, robot_id, with_skill=n < 2)
    robot_of(dave, "dave-bot", with_skill=False)
    return {"server": daphne_server, "carol": carol_key, "dave": dave_key}


def get(fleet: dict[str, Any], path: str, who: str = "carol") -> Any:
    with client(fleet["server"], fleet[who]) as http:
        return http.get(path)


def test_without_parameters_the_fleet_is_todays_bare_array_of_full_robots(fleet):
    answer = get(fleet, "/api/robot")
    assert answer.status_code == 200
    robots = answer.json()
    assert [robot["id"] for robot in robots] == ROBOTS
    assert set(robots[0]) == {
        "id",
        "name",
        "owner",
        "organization",
        "labels",
        "status",
        "connected",
        "last_seen",
        "ros_master",
        "ros2",
        "config",
        "skills",
    }
    assert robots[0]["skills"][0]["components"]


def test_pages_walk_the_fleet_in_id_order_with_count_and_links(fleet):
    seen = []
    path = "/api/robot?limit=3"
    while path:
        page = get(fleet, path).json()
        assert page["count"] == len(ROBOTS)
        seen += [robot["id"] for robot in page["results"]]
        path = page["next"]
    assert seen == ROBOTS

    middle = get(fleet, "/api/robot?limit=3&offset=3").json()
    assert [robot["id"] for robot in middle["results"]] == ROBOTS[3:6]
    assert "offset=0" in middle["previous"]
    assert "offset=6" in middle["next"]
    # A page's robots are the same documents as in the whole fleet.
    assert middle["results"] == get(fleet, "/api/robot").json()[3:6]


def test_a_page_past_the_end_is_empty_and_another_owners_robots_never_show(fleet):
    assert get(fleet, "/api/robot?offset=50").json() == {
        "count": 7,
        "next": None,
        "previous": get(fleet, "/api/robot?offset=50").json()["previous"],
        "results": [],
    }
    dave = get(fleet, "/api/robot?limit=10", who="dave").json()
    assert dave["count"] == 1
    assert [robot["id"] for robot in dave["results"]] == ["dave-bot"]


def test_fields_keep_only_the_asked_fields_of_each_robot(fleet):
    robots = get(fleet, "/api/robot?fields=id,connected").json()
    assert robots == [{"id": robot_id, "connected": False} for robot_id in ROBOTS]

    full = get(fleet, "/api/robot").json()
    with_skills = get(fleet, "/api/robot?fields=id,skills,owner&limit=2").json()["results"]
    assert with_skills == [{"id": r["id"], "owner": r["owner"], "skills": r["skills"]} for r in full[:2]]


def test_fields_and_connected_filter_together(fleet):
    assert get(fleet, "/api/robot?fields=id&connected=true").json() == []
    assert len(get(fleet, "/api/robot?fields=id&connected=false").json()) == len(ROBOTS)


@pytest.mark.parametrize(
    ("query", "field"),
    [
        ("limit=-1", "limit"),
        ("limit=0", "limit"),
        ("limit=100000", "limit"),
        ("limit=ten", "limit"),
        ("offset=-5", "offset"),
        ("fields=id,password", "fields"),
        ("fields=", "fields"),
        ("fields=id,,name", "fields"),
    ],
)
def test_bad_page_or_fields_parameters_are_a_clear_400(fleet, query, field):
    answer = get(fleet, f"/api/robot?{query}")
    assert answer.status_code == 400
    assert field in answer.json()
