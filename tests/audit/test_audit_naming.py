"""How the middleware names a request's action and object from its route: pure rules, no database."""

from __future__ import annotations

import pytest

from audit.choices import outcome_of
from audit.middleware import action_of, door_of, object_of


@pytest.mark.parametrize(
    ("url_name", "method", "action"),
    [
        ("robot-list", "POST", "robot.create"),
        ("robot-detail", "PATCH", "robot.update"),
        ("robot-detail", "DELETE", "robot.delete"),
        ("skill-start", "POST", "skill.start"),
        ("component-migrate", "POST", "component.migrate"),
        ("recording-detail", "DELETE", "recording.delete"),
        ("release-list", "POST", "release.create"),
        ("auth", "GET", "token.issue"),
        ("robot-token", "POST", "robot.token_rotate"),
        ("admin:robots_robot_change", "POST", "admin.robots_robot_change"),
        ("dashboard:member-add", "POST", "dashboard.member.add"),
        ("organization-members", "DELETE", "organization.members.delete"),
    ],
)
def test_an_action_is_named_by_its_route_and_method(url_name, method, action):
    assert action_of(url_name, method) == action


def test_an_object_is_the_path_of_the_routes_arguments():
    kwargs = {"robot_id": "r1", "skill_id": "s1", "component_id": "c"}
    assert object_of(kwargs, "component-migrate") == "robot/r1/skill/s1/component/c"
    assert object_of({"object_id": "7"}, "admin:auth_group_change") == "auth_group/7"
    assert object_of({"slug": "acme", "user_id": 3}, "member-detail") == "user/3"
    assert object_of({"slug": "acme"}, "organization-detail") == "organization/acme"


def test_doors_and_outcomes_follow_the_path_and_the_status():
    assert [door_of(path) for path in ("/api/robot", "/admin/x/", "/accounts/login/", "/orgs/")] == [
        "rest",
        "admin",
        "login",
        "dashboard",
    ]
    assert [outcome_of(status) for status in (200, 302, 401, 403, 404, 400, 409, 429, 500)] == [
        "ok",
        "ok",
        "denied",
        "denied",
        "not_found",
        "invalid",
        "invalid",
        "denied",
        "failed",
    ]
