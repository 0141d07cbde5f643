"""Listings cost a fixed number of database queries, however large the fleet."""

from __future__ import annotations

import pytest
from django.contrib.auth import get_user_model
from django.db import connection
from django.test.utils import CaptureQueriesContext
from rest_framework.test import APIClient

from skills.services import create_template

from .apiutil import robot_of, sample_skill_config

pytestmark = pytest.mark.django_db

ROUTES = ["/api/robot", "/api/robot/bot-0/info", "/api/events", "/api/templates"]


def queries_for(path: str, robots: int, *, staff: bool) -> int:
    """Count the queries one GET makes for a user owning this many robots, each with the sample Skill."""
    owner = get_user_model().objects.create_user(f"owner-{robots}")
    caller = get_user_model().objects.create_user(f"caller-{robots}", is_staff=True) if staff else owner
    for n in range(robots):
        robot_of(owner, f"bot-{n}")
    for n in range(robots):
        config = {**sample_skill_config(), "skill_id": f"skill-{robots}-{n}", "skill": f"Skill {n}"}
        create_template(name=f"Template {robots}-{n}", config=config)
    api = APIClient()
    api.force_authenticate(caller)
    with CaptureQueriesContext(connection) as queries:
        response = api.get(path)
    assert response.status_code == 200, response.content
    return len(queries)


@pytest.mark.parametrize("staff", [False, True], ids=["owner", "staff"])
@pytest.mark.parametrize("path", ROUTES)
def test_a_listing_makes_as_many_queries_for_20_robots_as_for_2(path, staff):
    small = queries_for(path, 2, staff=staff)
    # Start the large fleet from an empty database so nothing of the small one is counted.
    get_user_model().objects.all().delete()
    large = queries_for(path, 20, staff=staff)
    assert small == large, f"{path}: {small} queries for 2 robots, {large} for 20"
