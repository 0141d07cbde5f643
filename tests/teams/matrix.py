"""The role matrix: every route of the cloud, read from its routing, x every role and none x own organization and another's.

Each route has a rule: which kind of door it is, the right it needs and what it answers when the
caller may pass. The matrix asks every route with each of its methods as an anonymous caller, a
user with no role in the organization, and a viewer, an operator, a developer and an admin of it,
on an object of that organization and on one of another. The exact status follows from the rule:
another organization's object answers 404 as a missing one does, a missing role 403, and a held
right what the route answers when it works. A route without a rule fails the matrix, so a new door
cannot go unjudged. Every write that reaches a door's code leaves exactly one audit entry.

`run_matrix()` needs a migrated database it may write to (it makes and removes its own `mx-`
objects); the HTTP doors run in-process through Django's test client, the WebSocket doors over a
real socket when a daphne's `ws_url` is given.
"""

from __future__ import annotations

import contextlib
import json
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from teams.roles import Right

PREFIX = "mx-"
ROLES = ("viewer", "operator", "developer", "admin")
CALLERS = ("anonymous", "none", *ROLES)
TARGETS = ("own", "other")
SKILL = "people-detection"
COMPONENT = "sampler"
LEAST = {Right.READ: "viewer", Right.COMMAND: "operator", Right.DEVELOP: "developer", Right.ADMINISTER: "admin"}


@dataclass(frozen=True)
class Rule:
    """How one route is guarded, and what each of its methods answers a caller who may pass."""

    # robot: a robot's door; organization: an organization's (or its template's, member's, token's);
    # signed-in: any signed-in caller, answered from their own organizations; public: anyone;
    # staff: the admin site; secret: a door for a machine's secret (a cloud copy, the registry), never a user's.
    kind: str
    ok: dict[str, int]
    rights: dict[str, Right] = field(default_factory=dict)
    bodies: dict[str, Any] = field(default_factory=dict)
    # Methods that would spoil the shared objects (a delete, a removal) act on an object made for the case.
    fresh: frozenset[str] = frozenset()
    # An object only its holder and the organization's admins may know of: a missing role answers 404.
    hidden: bool = False
    # How a caller presents its API token: `token` (Authorization: Token), `basic` (the registry's
    # HTTP Basic, the token as password), `session` (a logged-in browser), `spent` (a session the call ends).
    auth: str = "token"
    # Whether a write here is an action the audit trail keeps (a form's validation, a machine's door are not).
    audited: bool = True
    # A listing of robots: it names exactly the robots of the caller's organizations.
    lists: bool = False

    def right(self, method: str) -> Right:
        return self.rights.get(method, Right.READ)


def robot(ok: dict[str, int], rights: dict[str, Right] | None = None, **kw: Any) -> Rule:
    return Rule("robot", ok, rights or {}, **kw)


def organization(ok: dict[str, int], rights: dict[str, Right] | None = None, **kw: Any) -> Rule:
    return Rule("organization", ok, rights or {}, **kw)


R, C, D, A = Right.READ, Right.COMMAND, Right.DEVELOP, Right.ADMINISTER
STEER = ("pause", "resume", "abort")
MIGRATE = {"location": "cloud"}

# Every HTTP route (its pattern as Django spells it) and its rule. The statuses of a route that
# works are what it answers on this matrix's objects: the robots are offline (a command answers
# 409), the recordings finished, the bodies as given.
HTTP_RULES: dict[str, Rule] = {
    # -- the dashboard's pages
    "": Rule("signed-in", {"GET": 200}, lists=True),
    "fleet/page": Rule("signed-in", {"GET": 200}, lists=True),
    "robots/<slug:robot_id>/": robot({"GET": 200}),
    "robots/<slug:robot_id>/logs/": robot({"GET": 200}),
    "skills/": Rule("signed-in", {"GET": 200}),
    "images/": Rule("signed-in", {"GET": 200}),
    "events/": Rule("signed-in", {"GET": 200}),
    "rollouts/": Rule("signed-in", {"GET": 200}),
    "rollouts/<int:rollout_id>/": organization({"GET": 200}),
    "organization": Rule("signed-in", {"POST": 302}),
    "organizations/": Rule("signed-in", {"GET": 200, "POST": 400}),
    "organizations/<str:slug>/": organization({"GET": 200, "POST": 400}, {"POST": A}, bodies={"POST": {}}),
    "organizations/<str:slug>/members/<str:username>": organization(
        {"POST": 302}, {"POST": A}, bodies={"POST": {"role": "operator"}}, fresh=frozenset({"POST"})
    ),
    "tokens/": Rule("signed-in", {"GET": 200, "POST": 400}),
    "tokens/<int:token_id>/revoke": organization({"POST": 302}, {"POST": A}, fresh=frozenset({"POST"}), hidden=True),
    "validate/skill-config": Rule("signed-in", {"GET": 405, "POST": 400}, audited=False),
    "validate/robot-config": Rule("signed-in", {"GET": 405, "POST": 400}, audited=False),
    "audit/": Rule("signed-in", {"GET": 200}),
    "accounts/login/": Rule("public", {"GET": 200, "POST": 200, "PUT": 200}, auth="session"),
    "accounts/logout/": Rule("public", {"GET": 405, "POST": 302}, auth="spent"),
    "admin/login/": Rule("public", {"GET": 200, "POST": 200}),
    "metrics": Rule("public", {"GET": 200}),
    # -- the Robot API: robots
    "api/health": Rule("public", {"GET": 200}),
    "api/auth": Rule("public", {"GET": 401, "POST": 401}),
    "api/auth/renew": Rule("signed-in", {"GET": 200, "POST": 200}),
    "api/robot": Rule("signed-in", {"GET": 200, "POST": 400}, lists=True),
    "api/robot/start": Rule("signed-in", {"POST": 200}),
    "api/robot/stop": Rule("signed-in", {"POST": 200}),
    "api/robot/shutdown": Rule("signed-in", {"POST": 200}),
    "api/robot/<slug:robot_id>": robot(
        {"GET": 200, "PATCH": 200, "DELETE": 204},
        {"PATCH": A, "DELETE": A},
        bodies={"PATCH": {"name": "Renamed"}},
        fresh=frozenset({"DELETE"}),
    ),
    "api/robot/<slug:robot_id>/info": robot({"GET": 200}),
    "api/robot/<slug:robot_id>/token": robot({"POST": 200}, {"POST": A}, bodies={"POST": {"grace_s": 60}}),
    "api/robot/<slug:robot_id>/bridge-ticket": robot({"POST": 200}, {"POST": C}),
    "api/robot/<slug:robot_id>/start": robot({"POST": 409}, {"POST": C}),
    "api/robot/<slug:robot_id>/stop": robot({"POST": 409}, {"POST": C}),
    "api/robot/<slug:robot_id>/shutdown": robot({"POST": 409}, {"POST": C}),
    "api/robot/<slug:robot_id>/vpn": robot({"GET": 409}, {"GET": A}),
    "api/robot/<slug:robot_id>/volumes": robot({"GET": 200}),
    # -- skills and components
    "api/robot/<slug:robot_id>/skill/add": robot({"POST": 400}, {"POST": D}, bodies={"POST": {}}),
    "api/robot/<slug:robot_id>/skill/remove": robot(
        {"POST": 204}, {"POST": D}, bodies={"POST": {"skill": SKILL}}, fresh=frozenset({"POST"})
    ),
    "api/robot/<slug:robot_id>/skill/<slug:skill_id>/info": robot({"GET": 200}),
    "api/robot/<slug:robot_id>/skill/<slug:skill_id>/start": robot({"POST": 409}, {"POST": C}),
    "api/robot/<slug:robot_id>/skill/<slug:skill_id>/stop": robot({"POST": 409}, {"POST": C}),
    "api/robot/<slug:robot_id>/skill/<slug:skill_id>/component/<slug:component_id>/info": robot({"GET": 200}),
    "api/robot/<slug:robot_id>/skill/<slug:skill_id>/component/<slug:component_id>/start": robot(
        {"POST": 409}, {"POST": C}, bodies={"POST": MIGRATE}
    ),
    "api/robot/<slug:robot_id>/skill/<slug:skill_id>/component/<slug:component_id>/stop": robot(
        {"POST": 409}, {"POST": C}
    ),
    "api/robot/<slug:robot_id>/skill/<slug:skill_id>/component/<slug:component_id>/migrate": robot(
        {"POST": 409}, {"POST": C}, bodies={"POST": MIGRATE}
    ),
    "api/cloud/manager/<str:token>/<path:path>": Rule("secret", {"GET": 400, "POST": 400}, audited=False),
    "api/templates": Rule("signed-in", {"GET": 200, "POST": 400}),
    "api/templates/<int:template_id>": organization(
        {"GET": 200, "DELETE": 204}, {"DELETE": D}, fresh=frozenset({"DELETE"})
    ),
    # -- metrics, events, recordings, the registry, organizations, tokens, the audit
    "api/database/query": Rule("signed-in", {"POST": 200}, audited=False),
    "api/events": Rule("signed-in", {"GET": 200}, lists=True),
    "api/robot/<slug:robot_id>/recordings": robot(
        {"GET": 200, "POST": 409}, {"POST": C}, bodies={"POST": {"topics": ["/chatter"]}}
    ),
    "api/robot/<slug:robot_id>/recordings/<slug:recording_id>": robot(
        {"GET": 200, "DELETE": 204}, {"DELETE": C}, fresh=frozenset({"DELETE"})
    ),
    "api/robot/<slug:robot_id>/recordings/<slug:recording_id>/stop": robot({"POST": 400}, {"POST": C}),
    "api/robot/<slug:robot_id>/recordings/<slug:recording_id>/download": robot({"GET": 409}),
    "api/robot/<slug:robot_id>/logs": robot({"GET": 200}),
    "api/robot/<slug:robot_id>/logs/download": robot({"GET": 200}),
    "api/registry/token": Rule("signed-in", {"GET": 200}, auth="basic"),
    "api/registry/events": Rule("secret", {"POST": 403}, audited=False),
    "api/registry/repositories": Rule("signed-in", {"GET": 200}),
    "api/organizations": Rule("signed-in", {"GET": 200, "POST": 400}),
    "api/organizations/<str:slug>": organization({"GET": 200}),
    "api/organizations/<str:slug>/members": organization({"GET": 200, "POST": 400}, {"POST": A}, bodies={"POST": {}}),
    "api/organizations/<str:slug>/members/<str:username>": organization(
        {"PATCH": 200, "DELETE": 204},
        {"PATCH": A, "DELETE": A},
        bodies={"PATCH": {"role": "operator"}},
        fresh=frozenset({"PATCH", "DELETE"}),
    ),
    "api/organizations/<str:slug>/tokens": organization({"GET": 200}, {"GET": A}),
    "api/tokens": Rule("signed-in", {"GET": 200, "POST": 400}),
    "api/tokens/<int:token_id>": organization({"DELETE": 204}, {"DELETE": A}, fresh=frozenset({"DELETE"}), hidden=True),
    "api/audit": Rule("signed-in", {"GET": 200}),
    "api/releases": Rule("signed-in", {"GET": 200, "POST": 400}),
    "api/releases/<int:release_id>": organization({"GET": 200}),
    "api/rollouts": Rule("signed-in", {"GET": 200, "POST": 400}),
    "api/rollouts/<int:rollout_id>": organization({"GET": 200}),
    # The matrix's rollouts are finished: steering one is a conflict.
    **{f"api/rollouts/<int:rollout_id>/{verb}": organization({"POST": 409}, {"POST": D}) for verb in STEER},
    "api/robot/<slug:robot_id>/hold": robot(
        {"GET": 200, "POST": 400, "DELETE": 204}, {"POST": C, "DELETE": C}, bodies={"POST": {}}
    ),
    "api/schema/": Rule("public", {"GET": 200}),
    "api/docs/": Rule("public", {"GET": 200}),
}
# The admin site's own routes answer its staff alone: everyone else is sent to its login.
ADMIN_RULE = Rule("staff", {"GET": 200})

# Every event a client may send on /ws/client/, and the data it is sent with.
CLIENT_EVENTS: dict[str, dict[str, Any]] = {
    "robot_start": {},
    "robot_stop": {},
    "shutdown": {},
    "robot_config_get": {},
    "robot_config_update": {"changes": {"offloading": "auto"}},
    "offloading": {"mode": "auto"},
    "offloading_get": {},
    "skill_start": {"skill": SKILL},
    "skill_stop": {"skill": SKILL},
    "skill_status_get": {"skill": SKILL},
    "skill_config_get": {"skill": SKILL},
    "component_start": {"skill": SKILL, "component": COMPONENT, "location": "cloud"},
    "component_stop": {"skill": SKILL, "component": COMPONENT},
    "component_status_get": {"skill": SKILL, "component": COMPONENT},
    "component_migrate": {"skill": SKILL, "component": COMPONENT, "location": "cloud"},
    "metrics_get": {},
    "logs_subscribe": {"tail": 0},
    "logs_unsubscribe": {},
    # Sent as {"robots": [the robot]}: a subscription names many robots, not one (wsmatrix.client_data).
    "metrics_subscribe": {},
}


# --------------------------------------------------------------------------- the routing, read


def http_routes() -> Iterator[tuple[str, Any]]:
    """Every URL pattern the cloud serves, as (pattern, view), the admin site's included."""
    from django.urls import URLPattern, URLResolver, get_resolver

    def walk(patterns: list, prefix: str) -> Iterator[tuple[str, Any]]:
        for pattern in patterns:
            if isinstance(pattern, URLResolver):
                yield from walk(pattern.url_patterns, prefix + str(pattern.pattern))
            elif isinstance(pattern, URLPattern):
                yield prefix + str(pattern.pattern), pattern.callback

    yield from walk(get_resolver().url_patterns, "")


def websocket_routes() -> list[str]:
    """Every WebSocket route of the cloud's ASGI routing."""
    from bridgeos_cloud.routing import websocket_urlpatterns

    return [str(pattern.pattern) for pattern in websocket_urlpatterns]


def view_methods(view: Any) -> set[str] | None:
    """The methods a class-based view answers; None for a function view (its rule says)."""
    cls = getattr(view, "cls", None) or getattr(view, "view_class", None)
    if cls is None:
        return None
    return {m.upper() for m in ("get", "post", "put", "patch", "delete") if hasattr(cls, m)}


def client_events() -> set[str]:
    """Every event a client may send that asks something of a robot (authentication and acks aside)."""
    from bridgeos_agent.protocol import DIRECTIONS, Direction, Event

    plumbing = {Event.AUTHENTICATION_CLIENT, Event.ACK, Event.ERROR_MESSAGE}
    return {str(e) for e, ways in DIRECTIONS.items() if Direction.CLIENT_TO_CLOUD in ways and e not in plumbing}


def unruled() -> list[str]:
    """Routes, methods and client events the matrix has no rule for, or rules for what no longer exists."""
    missing: list[str] = []
    routes = dict(http_routes())
    for route, view in routes.items():
        if route.startswith("admin/") and route != "admin/login/":
            continue
        rule = HTTP_RULES.get(route)
        if rule is None:
            missing.append(f"HTTP {route}: no rule")
            continue
        methods = view_methods(view)
        if methods is not None and methods != set(rule.ok):
            missing.append(f"HTTP {route}: the view answers {sorted(methods)}, the rule {sorted(rule.ok)}")
    missing += [f"HTTP {route}: a rule for no route" for route in HTTP_RULES if route not in routes]
    missing += [f"WS {route}: no rule" for route in websocket_routes() if route not in WS_ROUTES]
    missing += [f"WS event {event}: no rule" for event in client_events() - set(CLIENT_EVENTS)]
    return missing


WS_ROUTES = {"ws/robot/", "ws/rosbridge/<slug:robot_id>/", "ws/foxglove/<slug:robot_id>/", "ws/client/"}


# --------------------------------------------------------------------------- the world


@dataclass
class World:
    """The matrix's organizations, callers and objects."""

    organizations: dict[str, Any]  # own, other
    tokens: dict[str, str]  # caller -> API token
    users: dict[str, Any]  # caller -> user
    robot_tokens: dict[str, str]  # robot id -> its token
    templates: dict[str, int]  # target -> template id
    recordings: dict[str, str]  # target -> recording id
    copy_tokens: dict[str, str]  # target -> a cloud copy's token
    staff: Any = None
    made: int = 0
    releases: dict[str, int] = field(default_factory=dict)  # target -> release id
    rollouts: dict[str, int] = field(default_factory=dict)  # target -> a finished rollout's id

    def robot_id(self, target: str) -> str:
        return f"{PREFIX}{target}-bot"

    def member(self, target: str) -> str:
        return f"{PREFIX}{target}-member"


def clear() -> None:
    """Remove what an earlier matrix left."""
    from django.contrib.auth import get_user_model

    from robots.models import Robot
    from skills.models import SkillTemplate
    from teams.models import Organization

    Robot.objects.filter(id__startswith=PREFIX).delete()
    SkillTemplate.objects.filter(name__startswith=PREFIX).delete()
    Organization.objects.filter(slug__startswith=PREFIX).delete()
    get_user_model().objects.filter(username__startswith=PREFIX).delete()


def make_world() -> World:
    """Make two organizations with a robot each (a Skill, a cloud copy, a recording), a template, a release, the callers."""
    from django.contrib.auth import get_user_model

    from bridgeos_agent.skillconfig import load_sample_skill_config
    from recordings.choices import RecordingStatus
    from recordings.models import Recording
    from robots.services import create_robot, issue_api_token
    from rollouts.models import Rollout
    from rollouts.services import create_release
    from skills.models import CloudInstance, Component
    from skills.services import add_skill, create_template
    from teams.models import Membership, Organization

    clear()
    User = get_user_model()
    organizations = {t: Organization.objects.create(slug=f"{PREFIX}{t}", name=f"Matrix {t}") for t in TARGETS}
    users, tokens = {}, {}
    for caller in ("none", *ROLES):
        users[caller] = User.objects.create_user(f"{PREFIX}{caller}")
        if caller in ROLES:
            Membership.objects.create(organization=organizations["own"], user=users[caller], role=caller)
        tokens[caller] = issue_api_token(users[caller])[0]
    staff = User.objects.create_user(f"{PREFIX}staff", is_staff=True, is_superuser=True)
    config = load_sample_skill_config().model_dump(mode="json")
    robot_tokens, templates, recordings, copy_tokens, releases, rollouts = {}, {}, {}, {}, {}, {}
    for target, org in organizations.items():
        member = User.objects.create_user(f"{PREFIX}{target}-member")
        Membership.objects.create(organization=org, user=member, role="viewer")
        keeper = users["admin"]
        if target == "other":
            keeper = User.objects.create_user(f"{PREFIX}other-admin")
            Membership.objects.create(organization=org, user=keeper, role="admin")
        robot_id = f"{PREFIX}{target}-bot"
        made, robot_tokens[robot_id] = create_robot(robot_id, keeper, organization=org)
        add_skill(made, config)
        component = Component.objects.get(skill__robot=made, skill__skill_id=SKILL, component_id=COMPONENT)
        copy_tokens[target] = f"mxcopy{target}{made.pk}"
        CloudInstance.objects.update_or_create(
            component=component, defaults={"desired": CloudInstance.Desired.RUNNING, "token": copy_tokens[target]}
        )
        recording = Recording.objects.create(
            robot=made, topics=["/chatter"], status=RecordingStatus.FINISHED, max_bytes=1, max_duration_s=1
        )
        recordings[target] = recording.id.hex
        template_config = {**config, "skill_id": f"{PREFIX}{target}", "skill": f"{PREFIX}{target}"}
        templates[target] = create_template(name=f"{PREFIX}{target}", config=template_config, organization=org).pk
        made_release = create_release(org, pinned(template_config), user=keeper)
        releases[target] = made_release.pk
        rollouts[target] = Rollout.objects.create(
            organization=org, release=made_release, selector="site=matrix", state=Rollout.State.ROLLED_BACK
        ).pk
    world = World(organizations, tokens, users, robot_tokens, templates, recordings, copy_tokens, staff, 0, releases)
    world.rollouts = rollouts
    return world


def pinned(config: dict[str, Any]) -> dict[str, Any]:
    """Return a Skill config with every image pinned to a made-up digest, as a release needs."""
    components = {
        name: {
            **component,
            **{
                where: {**component[where], "image": component[where]["image"].split("@")[0] + "@sha256:" + "0" * 64}
                for where in ("robot", "cloud")
                if (component.get(where) or {}).get("image")
            },
        }
        for name, component in config["components"].items()
    }
    return {**config, "components": components}


def fresh_values(world: World, route: str, target: str) -> dict[str, str]:
    """Make the object a destructive case acts on; return the route's values that name it."""
    from django.contrib.auth import get_user_model

    from bridgeos_agent.skillconfig import load_sample_skill_config
    from recordings.choices import RecordingStatus
    from recordings.models import Recording
    from robots.services import create_robot, issue_api_token
    from skills.services import add_skill, create_template
    from teams.models import Membership

    world.made += 1
    org = world.organizations[target]
    name = f"{PREFIX}{target}-fresh-{world.made}"
    config = load_sample_skill_config().model_dump(mode="json")
    if "<slug:robot_id>" in route:
        keeper = org.memberships.get(role="admin").user
        made, world.robot_tokens[name] = create_robot(name, keeper, organization=org)
        add_skill(made, config)
        recording = Recording.objects.create(
            robot=made, topics=["/chatter"], status=RecordingStatus.FINISHED, max_bytes=1, max_duration_s=1
        )
        return {"robot_id": name, "recording_id": recording.id.hex}
    if "<int:template_id>" in route:
        return {
            "template_id": str(create_template(name=name, config={**config, "skill_id": name}, organization=org).pk)
        }
    member = get_user_model().objects.create_user(name)
    Membership.objects.create(organization=org, user=member, role="viewer")
    if "<int:token_id>" in route:
        return {"token_id": str(issue_api_token(member, organization=org, role="viewer", name="mx")[1].pk)}
    return {"username": name}


def fill(world: World, route: str, target: str, values: dict[str, str] | None = None) -> str:
    """The URL of a route with its values naming the target organization's objects."""
    from robots.models import ApiToken

    member_token = ApiToken.objects.filter(user__username=world.member(target)).values_list("pk", flat=True).first()
    known = {
        "robot_id": world.robot_id(target),
        "skill_id": SKILL,
        "component_id": COMPONENT,
        "recording_id": world.recordings[target],
        "template_id": str(world.templates[target]),
        "release_id": str(world.releases[target]),
        "rollout_id": str(world.rollouts[target]),
        "slug": world.organizations[target].slug,
        "username": world.member(target),
        "token_id": str(member_token or 0),
        "token": world.copy_tokens[target],
        "path": "status",
        **(values or {}),
    }
    return "/" + re.sub(r"<(?:\w+:)?(\w+)>", lambda m: known[m.group(1)], route)


# --------------------------------------------------------------------------- the judgement


def expected(rule: Rule, method: str, caller: str, target: str, page: bool) -> int:
    """The exact status a caller gets from a route's method on the target organization's object."""
    if rule.kind == "public" or rule.kind == "secret":
        return rule.ok[method]
    if caller == "anonymous":
        if rule.ok[method] == 405:
            return 405 if not page else 302
        return 302 if page else 401
    if rule.kind == "staff":
        return 302
    if rule.kind == "signed-in":
        return rule.ok[method]
    if rule.ok[method] == 405:
        return 405
    if target == "other" or caller == "none":
        return 404
    from teams.roles import RANK, Role

    least = LEAST[rule.right(method)]
    if RANK[Role(caller)] >= RANK[Role(least)]:
        return rule.ok[method]
    return 404 if rule.hidden else 403


@dataclass
class Tally:
    """Cases asked, and those whose answer differs from the rules'."""

    cases: int = 0
    failed: list[str] = field(default_factory=list)

    def judge(self, case: str, got: Any, want: Any) -> None:
        self.cases += 1
        if got != want:
            self.failed.append(f"{case}: {got}, the rule says {want}")


def ask_http(world: World, tally: Tally) -> None:
    """Ask every HTTP route and method as every caller on both organizations' objects."""

    from audit.models import AuditEntry

    clients: dict[Any, Any] = {}
    for route, _ in sorted(http_routes(), key=lambda pair: pair[0]):
        admin = route.startswith("admin/") and route != "admin/login/"
        rule = ADMIN_RULE if admin else HTTP_RULES[route]
        page = not route.startswith("api/")
        for method in sorted(rule.ok):
            for caller in CALLERS:
                for target in TARGETS:
                    if rule.kind not in ("robot", "organization") and target == "other":
                        continue  # a door without an object: asked once per caller
                    values = fresh_values(world, route, target) if method in rule.fresh else None
                    url = fill(world, route, target, values) if not admin else admin_url(route)
                    auth = rule.auth if not page or rule.auth == "spent" else "session"
                    client = caller_client(world, caller, auth, clients)
                    body = rule.bodies.get(method, {})
                    before = AuditEntry.objects.count()
                    # Each login attempt from its own address: the matrix's failed logins must not trip the
                    # brute-force limit (its own tests prove it) and turn later answers into 429s.
                    extra = {"REMOTE_ADDR": f"198.18.{tally.cases // 250}.{tally.cases % 250 + 1}"}
                    if page and method == "POST":
                        response = client.post(url, body, **extra)
                    else:
                        response = client.generic(
                            method, url, json.dumps(body) if method != "GET" else "", "application/json"
                        )
                    want = expected(rule, method, caller, target, page)
                    case = f"{caller} {method} {url} ({target})"
                    tally.judge(case, response.status_code, want)
                    if want == 404 and rule.kind in ("robot", "organization") and response.status_code == 404:
                        tally.judge(f"{case} body", not_found_body(response), "not found")
                    if rule.kind == "signed-in" and method == "GET":
                        names, may = shown(world, response), seen_by(caller)
                        tally.judge(
                            f"{case} robots shown", names if rule.lists else names - may, may if rule.lists else set()
                        )
                    if method != "GET" and rule.audited and audited(route, caller, response.status_code):
                        tally.judge(f"{case} audit entries", AuditEntry.objects.count() - before, 1)


def caller_client(world: World, caller: str, auth: str, clients: dict[Any, Any]) -> Any:
    """A test client that presents a caller's credential the way the door takes it (one per caller and way)."""
    import base64

    from django.test import Client

    # Each new test client builds the middleware again, whitenoise's scan of the static files
    # included: made once per caller and way, the matrix runs in a third of the time.
    client = clients.get((caller, auth))
    if client is None:
        client = clients[caller, auth] = Client(SERVER_NAME="localhost")
        key = world.tokens.get(caller)
        if auth == "session" and caller != "anonymous":
            client.force_login(world.users[caller])
        elif key and auth == "basic":
            pair = base64.b64encode(f"{world.users[caller].username}:{key}".encode()).decode()
            client.defaults["HTTP_AUTHORIZATION"] = f"Basic {pair}"
        elif key and auth == "token":
            client.defaults["HTTP_AUTHORIZATION"] = f"Token {key}"
    if auth == "spent" and caller != "anonymous":
        client.force_login(world.users[caller])  # the call logs it out: a new session each time
    return client


def admin_url(route: str) -> str:
    """A URL of an admin route: its pattern with harmless values."""
    values = {"app_label": "robots", "object_id": "missing", "content_type_id": "1", "url": "missing"}
    url = re.sub(r"<(?:\w+:)?(\w+)>", lambda m: values.get(m.group(1), "1"), route)
    url = re.sub(r"[\^$]|\(\?P<(\w+)>[^)]*\)", lambda m: values.get(m.group(1) or "", "") if m.group(1) else "", url)
    return "/" + url


def shown(world: World, response: Any) -> set[str]:
    """The matrix's robots a listing's answer names."""
    text = response.content.decode(errors="replace")
    return {target for target in TARGETS if world.robot_id(target) in text}


def seen_by(caller: str) -> set[str]:
    """The matrix's robots a caller may see: those of the organization they have a role in."""
    return {"own"} if caller in ROLES else set()


def not_found_body(response: Any) -> str:
    """Tell whether a 404's body says only what a missing object's would."""
    text = response.content.decode(errors="replace")
    return "not found" if PREFIX not in text.replace(response.wsgi_request.path, "") else f"leaks: {text[:200]}"


def audited(route: str, caller: str, status: int) -> bool:
    """Tell whether a write must leave one audit entry: a signed-in caller's, answered by the door's code."""
    return caller != "anonymous" and status != 405 and not route.startswith(("accounts/", "admin/login/"))


def run_matrix(ws_url: str | None = None) -> dict[str, Any]:
    """Run the matrix; return its cases, violations and the failed cases."""
    tally = Tally()
    missing = unruled()
    world = make_world()
    try:
        ask_http(world, tally)
        if ws_url is not None:
            from tests.teams.wsmatrix import ask_websockets

            ask_websockets(world, tally, ws_url)
    finally:
        with contextlib.suppress(Exception):
            clear()
    failed = missing + tally.failed
    return {"cases": tally.cases, "violations": len(failed), "failed": failed}
