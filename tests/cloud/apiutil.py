"""Helpers for Robot API tests: users, robots and HTTP clients against the real daphne."""

from __future__ import annotations

from typing import Any

import httpx
from asgiref.sync import sync_to_async
from django.contrib.auth import get_user_model

from bridgeos_agent.skillconfig import load_sample_skill_config
from robots.services import create_robot, issue_api_token
from skills.services import add_skill

SKILL = "people-detection"


def sample_skill_config() -> dict[str, Any]:
    """Return the sample people-detection Skill config as JSON-ready data."""
    return load_sample_skill_config().model_dump(mode="json")


def user_with_token(username: str, *, staff: bool = False, password: bool = False) -> tuple[Any, str]:
    """Create a user and return it with an API token; with a password `<username>-pass-123` if asked."""
    # Hashing a password takes a good part of a second, so only tests of /api/auth ask for one.
    secret = f"{username}-pass-123" if password else None
    user = get_user_model().objects.create_user(username, password=secret, is_staff=staff)
    return user, issue_api_token(user)[0]


def robot_of(owner: Any, robot_id: str, *, with_skill: bool = True) -> str:
    """Create a robot (with the sample Skill) and return its token."""
    robot, token = create_robot(robot_id, owner)
    if with_skill:
        add_skill(robot, sample_skill_config())
    return token


make_owner = sync_to_async(user_with_token)
make_robot = sync_to_async(robot_of)


def headers(token: str | None) -> dict[str, str]:
    """Return the Authorization header for an API (or robot) token, none for anonymous."""
    return {"Authorization": f"Token {token}"} if token else {}


def client(server: Any, token: str | None = None, **kw: Any) -> httpx.Client:
    """Return an HTTP client for the API that sends this token."""
    return httpx.Client(base_url=server.url, headers=headers(token), timeout=15, **kw)


def async_client(server: Any, token: str | None = None, **kw: Any) -> httpx.AsyncClient:
    """Return an async HTTP client for the API that sends this token."""
    return httpx.AsyncClient(base_url=server.url, headers=headers(token), timeout=15, **kw)
