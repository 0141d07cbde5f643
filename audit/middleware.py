"""Write one audit entry for every state-changing request to the Robot API, the admin and the dashboard."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from django.http import HttpRequest, HttpResponse

from . import services
from .choices import Door, Outcome

WRITES = frozenset({"POST", "PUT", "PATCH", "DELETE"})
# Routes that change state on a read: /api/auth issues a token on GET too.
ISSUING_READS = frozenset({"auth", "auth-renew"})
# Written elsewhere, once: registry pushes by the registry's notifications (one entry per tag), logins by
# the auth signals; the robot-side Components API is a robot's own door, not a person's.
SKIPPED = frozenset(
    {
        "registry-events",
        "cloud-components-api",
        "login",
        "logout",
        "dashboard:validate-skill-config",
        "dashboard:validate-robot-config",
        "database-query",  # a metrics query: a read sent as POST for its body
    }
)
NAMED_ACTIONS = {"auth": "token.issue", "auth-renew": "token.renew", "robot-token": "robot.token_rotate"}
# The URL arguments that name an object, in the order its path is written.
OBJECT_PARTS = (
    ("organization_slug", "organization"),
    ("robot_id", "robot"),
    ("skill_id", "skill"),
    ("component_id", "component"),
    ("recording_id", "recording"),
    ("template_id", "template"),
    ("member_id", "member"),
    ("token_id", "token"),
)
AUDITED = "_bridgeos_audited"
DESCRIBED = "_bridgeos_audit_described"


def mark_audited(request: Any) -> None:
    """Say a request's action was written already (by a signal), so the middleware does not write it again."""
    setattr(getattr(request, "_request", request), AUDITED, True)


def describe(request: Any, action: str, target: str, **data: Any) -> None:
    """Name a request's action and object more exactly than its route can (which member was added, as what)."""
    setattr(getattr(request, "_request", request), DESCRIBED, (action, target, data))


def attribute(request: Any, organization_id: int, slug: str) -> None:
    """Say which organization a request acts in when its route does not name it (a release made in one)."""
    getattr(request, "_request", request)._bridgeos_audit_organization = (organization_id, slug)


def door_of(path: str) -> Door:
    """Name the door a path belongs to."""
    if path.startswith("/api/"):
        return Door.REST
    if path.startswith("/admin/"):
        return Door.ADMIN
    if path.startswith("/accounts/"):
        return Door.LOGIN
    return Door.DASHBOARD


def action_of(url_name: str, method: str) -> str:
    """Name a request's action from its route's name and method: robot-detail DELETE is robot.delete."""
    if url_name in NAMED_ACTIONS:
        return NAMED_ACTIONS[url_name]
    namespace, _, name = url_name.rpartition(":")
    if namespace == "admin":
        return f"admin.{name}"  # e.g. admin.robots_robot_change
    base, _, kind = name.rpartition("-")
    if kind == "list" and method == "POST":
        return f"{base}.create"
    if kind in ("list", "detail"):
        return f"{base}.{'delete' if method == 'DELETE' else 'update'}"
    dotted = name.replace("-", ".", 1)
    suffix = {"DELETE": ".delete", "PUT": ".update", "PATCH": ".update"}.get(method, "")
    return f"{namespace}.{dotted}{suffix}" if namespace else f"{dotted}{suffix}"


ORGANIZATION_KEYS = ("organization_slug", "organization", "slug")


def object_of(kwargs: dict[str, Any], url_name: str) -> str:
    """Write the object a route's arguments name as a path: robot/r1/skill/s1/component/c."""
    parts = [f"{noun}/{kwargs[key]}" for key, noun in OBJECT_PARTS if key in kwargs]
    known = {key for key, _ in OBJECT_PARTS} | {"object_id", *ORGANIZATION_KEYS}
    # Routes added later (members, tokens, ...) still name their object, by their arguments' own names.
    parts += [f"{key.removesuffix('_id')}/{value}" for key, value in kwargs.items() if key not in known]
    if not parts and any(key in kwargs for key in ORGANIZATION_KEYS):
        parts.append(f"organization/{next(kwargs[key] for key in ORGANIZATION_KEYS if key in kwargs)}")
    if "object_id" in kwargs and url_name.startswith("admin:"):
        model = url_name.partition(":")[2].rsplit("_", 1)[0]  # robots_robot_change -> robots_robot
        parts.append(f"{model}/{kwargs['object_id']}")
    return "/".join(parts)


def actor_of(request: HttpRequest) -> tuple[str, str]:
    """Return who made a request (a username, or "") and the name of the API token it carried."""
    from robots.models import ApiToken

    user = getattr(request, "user", None)
    name = user.get_username() if user is not None and user.is_authenticated else ""
    token = getattr(request, "auth", None)
    token_name = (token.name or f"token-{token.pk}") if isinstance(token, ApiToken) else ""
    return name, token_name


class AuditTrail:
    """Write each state-changing request's action, object, outcome and author once, after its answer."""

    sync_capable = True
    async_capable = False

    def __init__(self, get_response: Callable[[HttpRequest], HttpResponse]) -> None:
        self.get_response = get_response

    def __call__(self, request: HttpRequest) -> HttpResponse:
        response = self.get_response(request)
        if request.method in WRITES or getattr(request.resolver_match, "url_name", None) in ISSUING_READS:
            if not getattr(request, AUDITED, False):
                self.write(request, response)
        return response

    def process_view(self, request: HttpRequest, view: Any, args: Any, kwargs: dict[str, Any]) -> None:
        """Note the robot's organization before the view runs: a deleted robot's is gone after."""
        if request.method not in WRITES:
            return
        if "robot_id" in kwargs:
            found = services.organization_of_robot(str(kwargs["robot_id"]))
        else:
            slug = next((str(kwargs[key]) for key in ORGANIZATION_KEYS if key in kwargs), None)
            if slug is None:
                return
            found = (services.organization_id(slug), slug)
        request._bridgeos_audit_organization = found  # type: ignore[attr-defined]

    def write(self, request: HttpRequest, response: HttpResponse) -> None:
        """Write a request's entry (the routes of other writers excepted)."""
        match = request.resolver_match
        # A route without a name (the admin's rate-limited login) has only its view's dotted path: not an action.
        url_name = match.view_name if match is not None and match.url_name else ""
        if url_name in SKIPPED or url_name.rpartition(":")[2] in SKIPPED:
            return
        door = door_of(request.path)
        method = request.method or ""
        kwargs = dict(match.kwargs) if match is not None else {}
        target = object_of(kwargs, url_name)
        data = getattr(response, "data", None)
        if not target and isinstance(data, dict) and isinstance(data.get("id"), str | int) and method == "POST":
            target = f"{url_name.rpartition('-')[0] or url_name}/{data['id']}"  # what a create made
        actor, token_name = actor_of(request)
        organization_id, organization_slug = getattr(request, "_bridgeos_audit_organization", (None, ""))
        status = response.status_code
        if organization_id is None and target.startswith("robot/") and status < 300:
            organization_id, organization_slug = services.organization_of_robot(target.split("/")[1])  # a new robot
        if organization_id is None:
            organization_id = self.scope_of(request)
            organization_slug = services.organization_slug(organization_id)
        action = action_of(url_name, method) if url_name else f"{door}.{method.lower()}"
        details: dict[str, Any] = {}
        if (described := getattr(request, DESCRIBED, None)) is not None:
            action, target, details = described
        outcome = None
        if door in (Door.ADMIN, Door.DASHBOARD) and status == 200:
            outcome = Outcome.INVALID  # a form shown again with its errors; a done change redirects
        services.record_quietly(
            action,
            door=door,
            actor=actor,
            token=token_name,
            address=request.META.get("REMOTE_ADDR", ""),
            target=target or ("" if url_name else request.path[:300]),
            status=status,
            outcome=outcome,
            organization_id=organization_id,
            organization_slug=organization_slug,
            data={"method": method, "path": request.path, **details},
        )

    @staticmethod
    def scope_of(request: HttpRequest) -> int | None:
        """Return the one organization a request acts in (its token's or session's pick), if any."""
        from robots.models import ApiToken

        token = getattr(request, "auth", None)
        if isinstance(token, ApiToken):
            return token.organization_id
        session = getattr(request, "session", None)
        from robots.access import SESSION_ORGANIZATION

        return session.get(SESSION_ORGANIZATION) if session is not None else None
