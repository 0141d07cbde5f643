"""Robot labels in the Django admin: edited on the robot's page (checked by the same rules), searched and filtered."""

from __future__ import annotations

import json

import pytest
from django.contrib.auth import get_user_model
from django.test import Client

from robots.models import Robot
from tests.teams.teamutil import robot_in, team

pytestmark = pytest.mark.django_db


@pytest.fixture
def staff_client() -> Client:
    ops = get_user_model().objects.create_user("ops", is_staff=True, is_superuser=True)
    client = Client()
    client.force_login(ops)
    return client


@pytest.fixture
def fleet() -> None:
    lab = team("lab", ada="admin")
    for robot_id, labels in {
        "lab-1": {"site": "lab", "model": "turtlebot"},
        "lab-2": {"site": "field", "model": "jackal"},
        "lab-3": {},
    }.items():
        robot_in(lab, robot_id)
        Robot.objects.filter(id=robot_id).update(labels=labels)


def change_form(robot: Robot, labels: str) -> dict[str, str]:
    """Return the admin change form of a robot as posted, with its labels field set to some text."""
    return {
        "name": robot.name,
        "organization": str(robot.organization_id),
        "owner": str(robot.owner_id or ""),
        "status": robot.status,
        "labels": labels,
        "config": json.dumps(robot.config),
    }


def test_staff_edit_a_robots_labels_on_its_admin_page(staff_client, fleet):
    robot = Robot.objects.get(id="lab-1")
    page = staff_client.get("/admin/robots/robot/lab-1/change/")
    assert page.status_code == 200
    assert b'name="labels"' in page.content
    saved = staff_client.post("/admin/robots/robot/lab-1/change/", change_form(robot, '{"site": "lab", "arm": "UR5e"}'))
    assert saved.status_code == 302, saved.content.decode()[:2000]
    assert Robot.objects.get(id="lab-1").labels == {"site": "lab", "arm": "UR5e"}


def test_bad_labels_in_the_admin_are_shown_at_the_field_and_change_nothing(staff_client, fleet):
    robot = Robot.objects.get(id="lab-1")
    refused = staff_client.post("/admin/robots/robot/lab-1/change/", change_form(robot, '{"Site": "lab"}'))
    assert refused.status_code == 200
    errors = refused.context["adminform"].form.errors
    assert list(errors) == ["labels"]
    assert "label key 'Site' is invalid" in errors["labels"][0]
    assert Robot.objects.get(id="lab-1").labels == {"site": "lab", "model": "turtlebot"}


def listed(page) -> list[str]:
    return sorted(robot.id for robot in page.context["cl"].result_list)


def test_the_robot_list_shows_labels_and_finds_robots_by_a_selector_a_label_or_its_text(staff_client, fleet):
    page = staff_client.get("/admin/robots/robot/")
    assert b"model=turtlebot, site=lab" in page.content
    assert listed(staff_client.get("/admin/robots/robot/", {"q": "site=lab"})) == ["lab-1"]
    assert listed(staff_client.get("/admin/robots/robot/", {"q": "model,site!=lab"})) == ["lab-2"]
    assert listed(staff_client.get("/admin/robots/robot/", {"q": "!site=x"})) == []
    assert listed(staff_client.get("/admin/robots/robot/", {"q": "jackal"})) == ["lab-2"]
    filters = page.context["cl"].filter_specs
    label_filter = next(spec for spec in filters if getattr(spec, "parameter_name", "") == "label")
    assert [choice for choice, _ in label_filter.lookup_choices] == [
        "model=jackal",
        "model=turtlebot",
        "site=field",
        "site=lab",
    ]
    assert listed(staff_client.get("/admin/robots/robot/", {"label": "site=field"})) == ["lab-2"]
