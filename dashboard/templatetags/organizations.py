"""The navigation's organization picker: the user's organizations and the one the session is held to."""

from __future__ import annotations

from typing import Any

from django import template

from robots import access
from teams.services import reachable_organizations

register = template.Library()


@register.inclusion_tag("dashboard/_picker.html", takes_context=True)
def organization_picker(context: dict[str, Any]) -> dict[str, Any]:
    """Render the picker of the request's user (staff pick among their own organizations too)."""
    request = context["request"]
    user = request.user
    actor = access.Actor(user)
    # Staff reach every organization; the picker lists only those they are members of, to stay short.
    mine = [(o, role) for o, role in reachable_organizations(actor) if o.id in actor.roles()]
    return {
        "organizations": mine,
        "picked": request.session.get(access.SESSION_ORGANIZATION),
        "next": request.get_full_path(),
        "csrf_token": context.get("csrf_token"),
    }
