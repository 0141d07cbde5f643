"""The doors of the cloud and the rules of who may pass: every route, and why a route takes no robot."""

from __future__ import annotations

import contextlib
import io
import re
from collections.abc import Iterator
from typing import Any

from benchmarks.chaos.hostile.world import SKILL, World


def http_routes() -> list[tuple[str, Any]]:
    """Every URL pattern the cloud serves (but the admin's own pages), as (route, callback)."""
    from django.urls import URLPattern, URLResolver, get_resolver

    def walk(patterns: list, prefix: str) -> Iterator[tuple[str, Any]]:
        for pattern in patterns:
            if isinstance(pattern, URLResolver):
                yield from walk(pattern.url_patterns, prefix + str(pattern.pattern))
            elif isinstance(pattern, URLPattern):
                yield prefix + str(pattern.pattern), pattern.callback

    return [
        (route, callback) for route, callback in walk(get_resolver().url_patterns, "") if not route.startswith("admin/")
    ]


def methods_of(callback: Any) -> list[str]:
    """The HTTP methods a view answers (GET and POST for a plain function view)."""
    view = getattr(callback, "cls", None) or getattr(callback, "view_class", None)
    if view is None:
        return ["GET", "POST"]
    return [m.upper() for m in ("get", "post", "put", "patch", "delete") if hasattr(view, m)]


# Routes that take no robot: what each gives and why no robot of another user can be reached there.
NO_ROBOT = {
    "": "the fleet page: lists only the user's robots (checked below)",
    "fleet/page": "a page of the fleet page's robots: only the user's, whatever it searches for (checked below)",
    "skills/": "the catalog of Skill templates, shared by design",
    "events/": "the event log page: filled by /api/events (checked below)",
    "rollouts/": "the rollouts of the caller's organizations (rollouts.rolling.visible_rollouts); names no robot",
    "rollouts/<int:rollout_id>/": "a rollout of the caller's organizations (404 otherwise), read as its API does",
    "images/": "the registry's images of the user's own namespace only (registry.services.repositories)",
    "validate/skill-config": "validates a posted config, touches no robot",
    "validate/robot-config": "validates a posted config, touches no robot",
    "accounts/login/": "login form",
    "accounts/logout/": "logout",
    "api/health": "liveness, no robot data",
    "metrics": "operator scrape, limited to BRIDGEOS_METRICS_ALLOW/TOKEN, not a per-user door",
    "api/auth": "exchanges a password for a token",
    "api/auth/renew": "renews the caller's own token",
    "api/registry/token": "grants repositories of the caller's own namespace only (tests/registry prove it)",
    "api/registry/events": "the registry's push notifications, refused without its notify token",
    "api/registry/repositories": "lists the caller's own namespace only (staff: all); tests/registry prove it",
    "api/templates": "the catalog and the caller's organizations' templates; writes are a developer's",
    "api/templates/<int:template_id>": "a template of the catalog or of the caller's organizations (404 otherwise)",
    "api/schema/": "the OpenAPI schema",
    "api/docs/": "the API docs page",
    # Doors of organizations, members and tokens: no robot in them; tests/teams prove another
    # organization answers 404 as a missing one does, and a missing role 403.
    "organization": "picks one of the caller's own organizations for the session",
    "organizations/": "the caller's own organizations",
    "organizations/<str:slug>/": "members of an organization of the caller's (404 otherwise)",
    "organizations/<str:slug>/members/<str:username>": "an admin's member change (404 outside, 403 below admin)",
    "tokens/": "the caller's own API tokens",
    "tokens/<int:token_id>/revoke": "revokes the caller's own token, or one of an organization they administer",
    "audit/": "the audit page: entries of organizations the caller administers (tests/audit)",
    "api/organizations": "the caller's own organizations; a new one has the caller as admin",
    "api/organizations/<str:slug>": "an organization of the caller's (404 otherwise)",
    "api/organizations/<str:slug>/members": "members of an organization of the caller's; changes are an admin's",
    "api/organizations/<str:slug>/members/<str:username>": "an admin's member change (404 outside, 403 below admin)",
    "api/organizations/<str:slug>/tokens": "an admin's list of the organization's tokens, without keys",
    "api/tokens": "the caller's own API tokens",
    "api/tokens/<int:token_id>": "revokes the caller's own token, or one of an organization they administer",
    "api/audit": "entries of organizations the caller administers (staff: all); tests/audit prove it",
    "api/releases": "releases of the caller's organizations, naming no robot; a new one is a developer's, in one",
    "api/releases/<int:release_id>": "a release of the caller's organizations (404 otherwise); it names no robot",
    "api/rollouts": "rollouts of the caller's organizations; a new one's selector reaches only the release's own "
    "organization's robots (tests/rollouts)",
    "api/rollouts/<int:rollout_id>": "a rollout of the caller's organizations (404 otherwise)",
    "api/rollouts/<int:rollout_id>/pause": "a developer's pause of their organization's rollout (404 outside)",
    "api/rollouts/<int:rollout_id>/resume": "a developer's resume of their organization's rollout (404 outside)",
    "api/rollouts/<int:rollout_id>/abort": "a developer's abort of their organization's rollout (404 outside)",
}
# Routes that take robots in the body or query string, or act on every robot the caller may see.
ROBOTS_IN_BODY = {
    "api/robot",
    "api/robot/start",
    "api/robot/stop",
    "api/robot/shutdown",
    "api/database/query",
    "api/events",
}

# Robot routes whose GET needs more than a viewer's role, and why: a viewer is refused them like any write.
PRIVILEGED_READS = {
    "api/robot/<slug:robot_id>/vpn": "the robot's VPN profile, with its private key: an admin's",
}
# Of those, the commands relayed to every robot the caller may command: a viewer's reaches none.
FLEET_COMMANDS = ("api/robot/start", "api/robot/stop", "api/robot/shutdown")


def is_read_request(event: str) -> bool:
    """Tell whether a request on /ws/client/ only reads (a viewer's right); every other one changes something."""
    return event.endswith("_get") or event in ("logs_subscribe", "logs_unsubscribe", "metrics_subscribe")


def published_robot_routes() -> set[str]:
    """The paths of the OpenAPI schema that name a robot: the resolver's enumeration must reach each."""
    from drf_spectacular.generators import SchemaGenerator

    with contextlib.redirect_stderr(io.StringIO()):  # drf-spectacular's naming warnings, printed elsewhere too
        paths = SchemaGenerator().get_schema(request=None, public=True)["paths"]
    return {path for path in paths if "{robot_id}" in path}


def fill_route(route: str, world: World, robot: str, copy_token: str) -> str:
    values = {
        "robot_id": robot,
        "skill_id": SKILL,
        "component_id": "sampler",
        "template_id": str(world.template_id),
        "token": copy_token,
        "path": "status",
        "recording_id": world.recording_id,
    }
    return "/" + re.sub(r"<(?:\w+:)?(\w+)>", lambda m: values[m.group(1)], route)


def destructive_rank(call: tuple[str, str]) -> int:
    """Order robot calls so what would remove a skill, cut alice-bot's link or delete it comes last, in that order."""
    route, method = call
    if method == "DELETE":
        return 3
    if route.endswith(("/token", "/shutdown")):
        return 2
    return 1 if route.endswith("/remove") else 0


def websocket_routes() -> list[str]:
    """Every WebSocket route of the cloud's own protocol (event, id and data frames), read from its routing."""
    from bridgeos_cloud.routing import websocket_urlpatterns

    return [str(p.pattern) for p in websocket_urlpatterns if "robot_id" not in str(p.pattern)]


def bridge_routes() -> list[str]:
    """The rosbridge and Foxglove doors of a robot: authorised at the handshake, their frames the robot's to read.

    Their bad input and floods are tested against a real agent (tests/cloud/test_bridge_relay.py);
    here every intruder's handshake on Alice's robot must be refused.
    """
    from bridgeos_cloud.routing import websocket_urlpatterns

    return [str(p.pattern) for p in websocket_urlpatterns if "robot_id" in str(p.pattern)]
