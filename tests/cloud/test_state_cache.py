"""The per-process robot state cache never serves stale state, even within one transaction."""

from __future__ import annotations

import pytest
from django.contrib.auth import get_user_model
from django.db import connection
from django.test.utils import CaptureQueriesContext
from rest_framework.test import APIClient

from robots.models import Robot
from skills.models import Component, Skill

from .apiutil import SKILL, robot_of

pytestmark = pytest.mark.django_db


@pytest.fixture
def api():
    """Return an API client of a user owning robot bot-1 (with the sample Skill) and bot-2 (none)."""
    owner = get_user_model().objects.create_user("cache-owner")
    robot_of(owner, "bot-1")
    robot_of(owner, "bot-2", with_skill=False)
    client = APIClient()
    client.force_authenticate(owner)
    return client


def fleet(api) -> dict:
    """Return the listed fleet as {robot id: state}."""
    response = api.get("/api/robot")
    assert response.status_code == 200, response.content
    return {robot["id"]: robot for robot in response.json()}


def components(state: dict) -> dict:
    """Return {component id: component} of the sample Skill in a robot's state."""
    (skill,) = [s for s in state["skills"] if s["skill_id"] == SKILL]
    return {c["component_id"]: c for c in skill["components"]}


def test_a_repeated_read_skips_building_the_json(api):
    fleet(api)
    with CaptureQueriesContext(connection) as cold:
        first = api.get("/api/robot").content
    Robot.objects.filter(id="bot-2").update(name="Renamed")
    with CaptureQueriesContext(connection) as warm:
        second = fleet(api)
    assert second["bot-2"]["name"] == "Renamed"
    assert len(warm) == len(cold) + 1, "one changed robot is rebuilt with one more query"
    with CaptureQueriesContext(connection) as hot:
        assert api.get("/api/robot").content != first
    assert len(hot) == len(cold)


def test_updates_within_one_transaction_are_seen(api):
    before = components(fleet(api)["bot-1"])
    name = next(iter(before))
    # The whole test runs in one transaction: every row version has the same xmin.
    Component.objects.filter(skill__robot_id="bot-1", component_id=name).update(status="running")
    assert components(fleet(api)["bot-1"])[name]["status"] == "running"
    Component.objects.filter(skill__robot_id="bot-1", component_id=name).update(status="stopped")
    assert components(fleet(api)["bot-1"])[name]["status"] == "stopped"


def test_added_and_removed_rows_and_the_owner_are_seen(api):
    fleet(api)
    skill = Skill.objects.get(robot_id="bot-1", skill_id=SKILL)
    Component.objects.create(skill=skill, component_id="extra", location="robot", resources={})
    assert "extra" in components(fleet(api)["bot-1"])
    Component.objects.filter(skill=skill, component_id="extra").delete()
    assert "extra" not in components(fleet(api)["bot-1"])
    skill.delete()
    assert fleet(api)["bot-1"]["skills"] == []
    get_user_model().objects.filter(username="cache-owner").update(username="cache-owner-2")
    assert {state["owner"] for state in fleet(api).values()} == {"cache-owner-2"}


def test_a_deleted_robot_disappears_and_info_agrees(api):
    fleet(api)
    Robot.objects.filter(id="bot-2").delete()
    assert list(fleet(api)) == ["bot-1"]
    assert api.get("/api/robot/bot-2/info").status_code == 404
    info = api.get("/api/robot/bot-1/info").json()
    assert info == fleet(api)["bot-1"]
