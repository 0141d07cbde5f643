"""`make run`'s demo fleet: robots with the demo Skill and fresh tokens on every run."""

from __future__ import annotations

import io
import json

import pytest
from django.contrib.auth import get_user_model
from django.core.management import CommandError, call_command

from robots.services import authenticate_robot
from skills.models import Skill

pytestmark = pytest.mark.django_db


def demo(count: int) -> dict:
    out = io.StringIO()
    call_command("demo_fleet", "--count", str(count), "--owner", "operator", stdout=out)
    return json.loads(out.getvalue())


def test_the_demo_fleet_is_made_once_and_gets_fresh_tokens_each_run():
    get_user_model().objects.create_user("operator")
    first = demo(2)
    assert [robot["id"] for robot in first["robots"]] == ["demo-1", "demo-2"]
    assert all(authenticate_robot(r["id"], r["token"]) is not None for r in first["robots"])
    second = demo(2)
    assert authenticate_robot("demo-1", first["robots"][0]["token"]) is None, "the old token is revoked"
    assert authenticate_robot("demo-1", second["robots"][0]["token"]) is not None
    assert Skill.objects.filter(robot_id__in=["demo-1", "demo-2"], skill_id="demo-telemetry").count() == 2
    assert first["api_token"] and first["api_token"] != second["api_token"]


def test_a_bad_count_or_owner_is_refused():
    with pytest.raises(CommandError, match="No user"):
        call_command("demo_fleet", "--owner", "nobody", stdout=io.StringIO())
    get_user_model().objects.create_user("operator")
    with pytest.raises(CommandError, match="between 0 and 500"):
        call_command("demo_fleet", "--owner", "operator", "--count", "-1", stdout=io.StringIO())
