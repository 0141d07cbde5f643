"""Helpers for the tests of teams: users, a team organization with members, robots in it."""

from __future__ import annotations

from typing import Any

from django.contrib.auth import get_user_model

from robots.services import create_robot, issue_api_token
from teams.models import Membership, Organization
from teams.roles import Role


def user(username: str, *, password: bool = False) -> Any:
    """Create a user (with their personal organization), with the password `<username>-pass-123` if asked."""
    # Hashing a password takes a good part of a second: only the browser's logins need one.
    return get_user_model().objects.create_user(username, password=f"{username}-pass-123" if password else None)


def login_token(who: Any) -> str:
    """Return a new login token of a user, acting with all their roles."""
    return issue_api_token(who)[0]


def team(slug: str, **members: str) -> Organization:
    """Create a team organization with users (by username) in roles."""
    organization = Organization.objects.create(slug=slug, name=slug.title())
    for username, role in members.items():
        found = get_user_model().objects.filter(username=username).first() or user(username)
        Membership.objects.create(organization=organization, user=found, role=Role(role))
    return organization


def robot_in(organization: Organization, robot_id: str) -> str:
    """Create a robot in an organization and return its token."""
    owner = organization.memberships.filter(role=Role.ADMIN).first()
    return create_robot(robot_id, owner.user if owner else None, organization=organization)[1]


def headers(token: str) -> dict[str, str]:
    """Return the Authorization header of an API token."""
    return {"Authorization": f"Token {token}"}
