"""The fleet page's data: a bounded page of the robots a user may see, searched, sorted and counted over the fleet."""

from __future__ import annotations

from datetime import timedelta

import pytest
from django.contrib.auth import get_user_model
from django.test import Client
from django.utils import timezone

from bridgeos_agent.skillconfig import load_sample_skill_config
from dashboard.forms import FleetQueryForm
from dashboard.services import FLEET_SORTS, FleetQuery, fleet_page
from monitoring.models import Metric
from robots.access import Actor
from robots.models import Robot, default_robot_config
from robots.services import create_robot
from skills.models import Component
from skills.services import add_skill
from teams.services import personal_organization

pytestmark = pytest.mark.django_db

ROBOTS = 250


@pytest.fixture
def fleet():
    """Alice owns 250 robots (every tenth online, fleet-0007 named "Kitchen helper"); Bob owns two."""
    users = get_user_model().objects
    alice = users.create_user("alice", password="alice-pass-123")
    bob = users.create_user("bob", password="bob-pass-123")
    organization, config = personal_organization(alice), default_robot_config()
    robots = []
    for i in range(ROBOTS):
        robot = Robot(id=f"fleet-{i:04d}", owner=alice, organization=organization, config=config)
        robot.connected = i % 10 == 0
        robot.name = "Kitchen helper" if i == 7 else ""
        robot.labels = {"site": "lab"} if i < 5 else {}
        robot.issue_token()
        robots.append(robot)
    Robot.objects.bulk_create(robots)
    create_robot("bob-1", bob, name="Kitchen helper")
    create_robot("fleet-bob", bob)
    return {"alice": Actor(alice), "bob": Actor(bob), "staff": Actor(users.create_user("ops", is_staff=True))}


def ids(page: dict) -> list[str]:
    return [row["id"] for row in page["robots"]]


def test_a_page_holds_a_hundred_robots_and_counts_the_whole_fleet(fleet):
    first = fleet_page(fleet["alice"], FleetQuery())
    assert ids(first)[:2] == ["fleet-0000", "fleet-0001"] and len(first["robots"]) == 100
    assert (first["count"], first["page"], first["pages"], first["offset"]) == (ROBOTS, 1, 3, 0)
    assert first["summary"] == {"robots": ROBOTS, "online": 25, "skills": 0, "on_robot": 0, "on_cloud": 0}
    last = fleet_page(fleet["alice"], FleetQuery(page=3))
    assert ids(last)[0] == "fleet-0200" and len(last["robots"]) == 50 and last["offset"] == 200
    # Past the end: the last page, not an empty one.
    assert fleet_page(fleet["alice"], FleetQuery(page=99))["page"] == 3
    assert fleet_page(fleet["staff"], FleetQuery())["summary"]["robots"] == ROBOTS + 2


def test_the_search_reaches_the_whole_fleet_but_only_robots_the_user_may_see(fleet):
    found = fleet_page(fleet["alice"], FleetQuery(text="kitchen"))
    assert ids(found) == ["fleet-0007"] and found["count"] == 1
    assert found["summary"]["robots"] == ROBOTS  # the fleet's counts, not the matches'
    assert ids(fleet_page(fleet["alice"], FleetQuery(text="fleet-024"))) == [f"fleet-024{i}" for i in range(10)]
    assert ids(fleet_page(fleet["alice"], FleetQuery(text="bob"))) == []
    assert ids(fleet_page(fleet["bob"], FleetQuery(text="kitchen"))) == ["bob-1"]
    assert ids(fleet_page(fleet["bob"], FleetQuery(text="fleet"))) == ["fleet-bob"]


def test_a_label_selector_and_the_connected_state_narrow_the_fleet(fleet):
    form = FleetQueryForm({"q": "site=lab", "state": "online"})
    assert ids(fleet_page(fleet["alice"], form.query())) == ["fleet-0000"]
    offline = fleet_page(fleet["alice"], FleetQuery(state="offline"))
    assert offline["count"] == ROBOTS - 25 and ids(offline)[0] == "fleet-0001"


def test_a_malformed_selector_matches_nothing_and_says_why(fleet):
    query = FleetQueryForm({"q": "Site=lab", "sort": "nonsense", "page": "0"}).query()
    assert "selector term 'Site=lab' is invalid" in query.error
    assert (query.sort, query.page) == ("id", 1)  # other bad parameters fall back to their defaults
    page = fleet_page(fleet["alice"], query)
    assert (page["robots"], page["count"], page["error"]) == ([], 0, query.error)
    assert page["summary"]["robots"] == ROBOTS


def test_every_sort_key_orders_the_whole_fleet(fleet):
    now = timezone.now()
    Metric.objects.bulk_create(
        [
            Metric(robot_id="fleet-0150", name="cpu", value=90.0, ts=now),
            Metric(robot_id="fleet-0150", name="cpu", value=5.0, ts=now - timedelta(minutes=1)),
            Metric(robot_id="fleet-0042", name="cpu", value=50.0, ts=now),
            # Older than an hour: not live, sorts as no value.
            Metric(robot_id="fleet-0003", name="cpu", value=99.0, ts=now - timedelta(hours=2)),
        ]
    )
    add_skill(Robot.objects.get(id="fleet-0120"), load_sample_skill_config().model_dump(mode="json"))
    Component.objects.filter(skill__robot_id="fleet-0120", component_id="detector").update(
        status="running", active_location="cloud"
    )
    Robot.objects.filter(id="fleet-0011").update(last_seen=now)
    alice = fleet["alice"]
    first = {
        sort: ids(fleet_page(alice, FleetQuery(sort=sort)))[:2] for key in FLEET_SORTS for sort in (key, f"-{key}")
    }
    assert first["-id"] == ["fleet-0249", "fleet-0248"]
    assert first["-cpu"] == ["fleet-0150", "fleet-0042"]
    assert first["cpu"] == ["fleet-0000", "fleet-0001"]
    assert first["connected"] == ["fleet-0000", "fleet-0010"]
    assert first["-skills"][0] == first["-components"][0] == "fleet-0120"
    assert first["-seen"] == ["fleet-0000", "fleet-0010"] and first["seen"][0] == "fleet-0001"
    assert ids(fleet_page(alice, FleetQuery(sort="-seen", state="offline")))[0] == "fleet-0011"
    counted = fleet_page(alice, FleetQuery())["summary"]
    assert (counted["skills"], counted["on_robot"], counted["on_cloud"]) == (1, 0, 1)


def test_the_page_door_answers_json_and_refuses_a_bad_selector(fleet):
    browser = Client()
    browser.force_login(fleet["bob"].user)
    answer = browser.get("/fleet/page", {"q": "kitchen"})
    assert answer.status_code == 200 and [row["id"] for row in answer.json()["robots"]] == ["bob-1"]
    refused = browser.get("/fleet/page", {"q": "Site=lab"})
    assert refused.status_code == 400 and "selector term 'Site=lab' is invalid" in refused.json()["q"][0]
    page = browser.get("/", {"q": "fleet", "page": "2"})
    assert page.status_code == 200 and page.context["fleet"]["count"] == 1
    assert Client().get("/fleet/page").status_code == 302  # to the login form
