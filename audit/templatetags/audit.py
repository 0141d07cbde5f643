"""Template filters of the audit trail."""

from __future__ import annotations

from typing import Any

from django import template

from robots.access import actor_of
from teams.roles import Right

register = template.Library()


@register.filter
def reads_audit(request: Any) -> bool:
    """Tell whether a request may read some of the audit trail (staff, or an admin of an organization)."""
    user = getattr(request, "user", None)
    if user is None or not user.is_authenticated:
        return False
    actor = actor_of(request)
    ids = actor.organization_ids()
    return ids is None or any(actor.may(org, Right.ADMINISTER) for org in ids)
