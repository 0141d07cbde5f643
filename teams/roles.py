"""The four roles of a member, in order, and what each may do: pure rules, no database."""

from __future__ import annotations

from enum import StrEnum

from django.db import models


class Role(models.TextChoices):
    """A member's role in an organization; each holds every right of the roles before it."""

    VIEWER = "viewer", "Viewer"
    OPERATOR = "operator", "Operator"
    DEVELOPER = "developer", "Developer"
    ADMIN = "admin", "Admin"


RANK = {role: rank for rank, role in enumerate(Role)}


class Right(StrEnum):
    """What a door asks of its caller; each right belongs to the least role that holds it."""

    READ = "read"  # everything of the organization, live views included
    COMMAND = "command"  # robot and Skill start/stop, migrations, recordings, bridges
    DEVELOP = "develop"  # Skills added or removed, templates, registry pushes, releases, rollouts
    ADMINISTER = "administer"  # members, robots, tokens, settings


LEAST_ROLE = {
    Right.READ: Role.VIEWER,
    Right.COMMAND: Role.OPERATOR,
    Right.DEVELOP: Role.DEVELOPER,
    Right.ADMINISTER: Role.ADMIN,
}


def holds(role: str | None, right: Right) -> bool:
    """Tell whether a role (None: no role) holds a right."""
    return role is not None and RANK[Role(role)] >= RANK[LEAST_ROLE[right]]


def lesser(role: str, cap: str | None) -> str:
    """Return a role limited by a cap (a token's role); None caps nothing."""
    if cap is None:
        return role
    return role if RANK[Role(role)] <= RANK[Role(cap)] else cap
