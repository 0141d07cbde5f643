"""Deleting robots in the Django admin: as the API deletes them, with all they own, and without loading it to list it."""

from __future__ import annotations

from datetime import timedelta

import pytest
from asgiref.sync import async_to_sync
from channels.layers import get_channel_layer
from django.contrib.auth import get_user_model
from django.contrib.auth.models import Permission
from django.db import connection
from django.test import Client
from django.test.utils import CaptureQueriesContext
from django.utils import timezone

from monitoring.models import Event, Metric
from network.models import Subnet
from robots.models import Robot
from tests.teams.teamutil import robot_in, team

pytestmark = pytest.mark.django_db

POINTS = 3000


@pytest.fixture
def fleet() -> None:
    lab = team("lab", ada="admin")
    for robot_id in ("lab-1", "lab-2", "lab-3"):
        robot_in(lab, robot_id)
    Robot.objects.filter(id="lab-1").update(name="Arm one")
    now = timezone.now()
    Metric.objects.bulk_create(
        Metric(robot_id=robot_id, name="cpu", value=float(i), ts=now - timedelta(seconds=i))
        for robot_id, points in (("lab-1", POINTS), ("lab-2", 7), ("lab-3", 5))
        for i in range(points)
    )
    Event.objects.bulk_create(Event(robot_id="lab-1", message=f"note {i}") for i in range(2))


def staff(*permissions: str) -> Client:
    """Return a client logged in as a staff user with these robot permissions (all of them if none are named)."""
    user = get_user_model().objects.create_user("ops", is_staff=True, is_superuser=not permissions)
    user.user_permissions.set(Permission.objects.filter(content_type__app_label="robots", codename__in=permissions))
    client = Client()
    client.force_login(user)
    return client


def deleted_events() -> list[str]:
    return sorted(event.data["robot"] for event in Event.objects.filter(kind="robot_deleted"))


def test_a_robots_admin_page_deletes_it_with_all_it_owns_and_closes_its_connection(
    fleet, django_capture_on_commit_callbacks
):
    client = staff()
    subnets = Subnet.objects.filter(robot_id="lab-1").count()
    events = Event.objects.filter(robot_id="lab-1").count()
    assert subnets and events >= 2
    with CaptureQueriesContext(connection) as queries:
        page = client.get("/admin/robots/robot/lab-1/delete/")
    assert page.status_code == 200
    text = page.content.decode()
    assert "Cannot delete" not in text and "doesn't have permission" not in text
    assert "Robot: Arm one (lab-1)" in text
    assert f"{POINTS} metrics" in text and f"{events} events" in text and f"{subnets} subnets" in text
    assert page.context["model_count"] and dict(page.context["model_count"])["metrics"] == POINTS
    # Counted, not loaded: no query reads the metric points themselves.
    metric_reads = [q["sql"] for q in queries if Metric._meta.db_table in q["sql"] and "COUNT(" not in q["sql"]]
    assert metric_reads == []
    layer = get_channel_layer()
    channel = async_to_sync(layer.new_channel)()
    Robot.objects.filter(id="lab-1").update(channel=channel, connected=True)
    with django_capture_on_commit_callbacks(execute=True):
        done = client.post("/admin/robots/robot/lab-1/delete/", {"post": "yes"})
    assert done.status_code == 302
    assert not Robot.objects.filter(id="lab-1").exists()
    assert not Metric.objects.filter(robot_id="lab-1").exists()
    assert not Subnet.objects.filter(robot_id="lab-1").exists()
    assert not Event.objects.filter(robot_id="lab-1").exists()
    assert Metric.objects.filter(robot_id="lab-2").count() == 7
    assert deleted_events() == ["lab-1"]
    # The robot's live connection is told it was revoked, as when the API deletes it.
    assert async_to_sync(layer.receive)(channel)["type"] == "robot.revoked"


def test_the_delete_action_counts_then_deletes_the_selected_robots_and_leaves_the_rest(fleet):
    client = staff()
    chosen = {"action": "delete_selected", "_selected_action": ["lab-1", "lab-2"]}
    page = client.post("/admin/robots/robot/", chosen)
    assert page.status_code == 200
    counts = dict(page.context["model_count"])
    assert counts["robots"] == 2 and counts["metrics"] == POINTS + 7
    assert "doesn't have permission" not in page.content.decode()
    done = client.post("/admin/robots/robot/", {**chosen, "post": "yes"})
    assert done.status_code == 302
    assert sorted(Robot.objects.values_list("id", flat=True)) == ["lab-3"]
    assert set(Metric.objects.values_list("robot_id", flat=True)) == {"lab-3"}
    assert deleted_events() == ["lab-1", "lab-2"]


def test_staff_without_the_robot_delete_permission_are_refused_and_nothing_changes(fleet):
    client = staff("view_robot", "change_robot")
    assert client.get("/admin/robots/robot/lab-1/delete/").status_code == 403
    assert client.post("/admin/robots/robot/lab-1/delete/", {"post": "yes"}).status_code == 403
    assert Robot.objects.filter(id="lab-1").exists()
    assert Metric.objects.filter(robot_id="lab-1").count() == POINTS
    assert deleted_events() == []
