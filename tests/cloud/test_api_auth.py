"""Who may call what on the Robot API: every route for anonymous, a robot, another user, the owner and staff."""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from datetime import timedelta
from typing import Any

import httpx
import pytest
from django.contrib.auth import get_user_model
from django.utils import timezone
from drf_spectacular.generators import SchemaGenerator

from monitoring.models import Metric
from recordings.choices import RecordingStatus
from recordings.models import Recording
from robots.models import ApiToken, BridgeTicket, Robot, hash_token
from robots.services import issue_api_token
from rollouts.models import Release, Rollout
from skills.models import Component, Skill, SkillTemplate
from skills.services import create_template
from teams.services import personal_organization

from .apiutil import SKILL, client, robot_of, sample_skill_config, user_with_token

pytestmark = pytest.mark.django_db(transaction=True)

ROBOT = "/api/robot/{robot_id}"
SKILL_PATH = ROBOT + "/skill/{skill_id}"
COMPONENT = SKILL_PATH + "/component/{component_id}"
RECORDING = ROBOT + "/recordings/{recording_id}"
ORG = "/api/organizations/{slug}"
REFUSED = {401, 403, 404}


@dataclass(frozen=True)
class Route:
    """One route and the status each kind of caller gets; the owner and staff act on different robots."""

    method: str
    path: str
    owner: int
    other: int
    staff: int
    body: dict[str, Any] | None = None
    # Listings must show the owner's robots to the owner and staff, and nothing of them to anyone else.
    lists: bool = False
    anonymous: int = 401
    ids: dict[str, str] = field(default_factory=dict)
    # A robot's token opens only the robot's own VPN profile.
    robot: int = 401


def new_template_config() -> dict[str, Any]:
    """Return a Skill config for the catalog whose skill no robot has yet."""
    return {**sample_skill_config(), "skill_id": "people-counting", "skill": "People counting"}


ROUTES = [
    # /api/auth exchanges a password, never an API token, for a token (see the Basic tests below).
    Route("GET", "/api/auth", 401, 401, 401),
    Route("POST", "/api/auth", 401, 401, 401),
    Route("GET", "/api/auth/renew", 200, 200, 200),
    Route("POST", "/api/auth/renew", 200, 200, 200),
    # The registry's token server takes Basic credentials only, as Distribution's clients send them
    # (tests/registry): an API token in a Token header is refused like no credentials at all.
    Route("GET", "/api/registry/token", 401, 401, 401),
    # Each caller's own namespace (tests/registry/test_notifications.py shows the listings differ).
    Route("GET", "/api/registry/repositories", 200, 200, 200),
    Route("GET", "/api/robot", 200, 200, 200, lists=True),
    Route("POST", "/api/robot", 201, 201, 201, body={"id": "{role}-made"}),
    Route("POST", "/api/robot/start", 200, 200, 200),
    Route("POST", "/api/robot/stop", 200, 200, 200),
    Route("POST", "/api/robot/shutdown", 200, 200, 200),
    Route("GET", ROBOT, 200, 404, 200),
    Route("PATCH", ROBOT, 200, 404, 200, body={"name": "renamed"}),
    Route("DELETE", ROBOT, 204, 404, 204),
    Route("GET", ROBOT + "/info", 200, 404, 200),
    Route("POST", ROBOT + "/token", 200, 404, 200),
    Route("GET", ROBOT + "/volumes", 200, 404, 200),
    # A browser's ticket for the robot's rosbridge and Foxglove doors in the cloud.
    Route("POST", ROBOT + "/bridge-ticket", 200, 404, 200),
    # Recordings: each robot has a finished one (no file kept); starting one needs the robot connected.
    Route("GET", ROBOT + "/recordings", 200, 404, 200),
    Route("POST", ROBOT + "/recordings", 409, 404, 409, body={"topics": ["/chatter"]}),
    Route("GET", RECORDING, 200, 404, 200),
    Route("POST", RECORDING + "/stop", 400, 404, 400),
    Route("GET", RECORDING + "/download", 409, 404, 409),
    # Component logs: read with the viewer role, another user's robot as if it did not exist.
    Route("GET", ROBOT + "/logs", 200, 404, 200),
    Route("GET", ROBOT + "/logs/download", 200, 404, 200),
    Route("DELETE", RECORDING, 204, 404, 204),
    # This cloud offers no VPN (BRIDGEOS_VPN_REMOTE unset): 409 to those who may ask.
    Route("GET", ROBOT + "/vpn", 409, 404, 409, robot=409),
    # Commands reach the robot only when it is connected; here it is not.
    Route("POST", ROBOT + "/start", 409, 404, 409),
    Route("POST", ROBOT + "/stop", 409, 404, 409),
    Route("POST", ROBOT + "/shutdown", 409, 404, 409),
    Route("POST", ROBOT + "/skill/add", 201, 404, 201, body={"template": "{template_id}"}),
    Route("POST", ROBOT + "/skill/remove", 204, 404, 204, body={"skill": SKILL}),
    Route("GET", SKILL_PATH + "/info", 200, 404, 200),
    Route("POST", SKILL_PATH + "/start", 409, 404, 409),
    Route("POST", SKILL_PATH + "/stop", 409, 404, 409),
    Route("GET", COMPONENT + "/info", 200, 404, 200),
    Route("POST", COMPONENT + "/start", 409, 404, 409, body={"location": "robot"}),
    Route("POST", COMPONENT + "/stop", 409, 404, 409, body={}),
    Route("POST", COMPONENT + "/migrate", 409, 404, 409, body={"location": "cloud"}),
    Route("GET", "/api/templates", 200, 200, 200),
    Route("POST", "/api/templates", 403, 403, 201, body={"name": "{role} template", "config": "{new_config}"}),
    Route("GET", "/api/templates/{template_id}", 200, 200, 200),
    Route("DELETE", "/api/templates/{template_id}", 403, 403, 204),
    Route("POST", "/api/database/query", 200, 200, 200, body={"kind": "events"}, lists=True),
    Route("POST", "/api/database/query", 200, 200, 200, body={"kind": "metrics"}, lists=True),
    Route("GET", "/api/events", 200, 200, 200, lists=True),
    Route("GET", "/api/health", 200, 200, 200, anonymous=200),
    # alice's personal organization; bob is no member of it, so to him it does not exist.
    Route("GET", "/api/organizations", 200, 200, 200, lists=False),
    Route("POST", "/api/organizations", 201, 201, 201, body={"slug": "{role}-team"}),
    Route("GET", ORG, 200, 404, 200),
    Route("GET", ORG + "/members", 200, 404, 200),
    Route("POST", ORG + "/members", 201, 404, 400, body={"username": "bob", "role": "viewer"}),
    Route("PATCH", ORG + "/members/{username}", 200, 404, 200, body={"role": "admin"}),
    Route("DELETE", ORG + "/members/{username}", 400, 404, 400),
    Route("GET", ORG + "/tokens", 200, 404, 200),
    Route("GET", "/api/tokens", 200, 200, 200),
    Route("POST", "/api/tokens", 201, 400, 201, body={"name": "ci", "organization": "alice", "role": "viewer"}),
    Route("DELETE", "/api/tokens/{token_id}", 404, 404, 404),
    # Each caller reads the entries of the organizations they administer (tests/audit shows which).
    Route("GET", "/api/audit", 200, 200, 200),
    # Releases of alice's organization: the sample's images are not pinned (no registry here), so a
    # new one is refused for that; to bob her organization does not exist.
    Route("GET", "/api/releases", 200, 200, 200),
    Route("POST", "/api/releases", 400, 404, 400, body={"organization": "alice", "config": "{new_config}"}),
    Route("GET", "/api/releases/{release_id}", 200, 404, 200),
    # A rollout of alice's release to a group of none of her robots is refused for its selector; to
    # bob the release does not exist. alice's one rollout is over: steering it is a conflict.
    Route("GET", "/api/rollouts", 200, 200, 200),
    Route("POST", "/api/rollouts", 400, 400, 400, body={"release": "{release_id}", "selector": "site=nowhere"}),
    Route("GET", "/api/rollouts/{rollout_id}", 200, 404, 200),
    Route("POST", "/api/rollouts/{rollout_id}/pause", 409, 404, 409),
    Route("POST", "/api/rollouts/{rollout_id}/resume", 409, 404, 409),
    Route("POST", "/api/rollouts/{rollout_id}/abort", 409, 404, 409),
    Route("GET", ROBOT + "/hold", 200, 404, 200),
    Route("POST", ROBOT + "/hold", 200, 404, 200, body={"seconds": 60}),
    Route("DELETE", ROBOT + "/hold", 204, 404, 204),
]


@dataclass
class World:
    """Alice owns alice-bot and alice-spare, Bob owns bob-bot, ops is staff; each holds an API token."""

    server: Any
    tokens: dict[str, str]
    robot_token: str
    template_id: int
    recordings: dict[str, str]  # robot id -> its finished recording's id
    release_id: int  # a release of alice's organization
    rollout_id: int  # a finished rollout of that release


@pytest.fixture
def world(daphne_server) -> World:
    users = {}
    tokens = {}
    for role, username, staff in (("owner", "alice", False), ("other", "bob", False), ("staff", "ops", True)):
        # No password: hashing one is slow, and these callers use API tokens.
        users[role] = get_user_model().objects.create_user(username, is_staff=staff)
        tokens[role] = issue_api_token(users[role])[0]
    robot_token = robot_of(users["owner"], "alice-bot")
    robot_of(users["owner"], "alice-spare")
    robot_of(users["other"], "bob-bot")
    a_minute_ago = timezone.now() - timedelta(minutes=1)
    Metric.objects.bulk_create(
        Metric(robot_id=robot_id, name="cpu", value=0.5, ts=a_minute_ago) for robot_id in ("alice-bot", "bob-bot")
    )
    template = create_template(name="People counting", config=new_template_config())
    recordings = {
        robot_id: Recording.objects.create(
            robot_id=robot_id, topics=["/chatter"], status=RecordingStatus.FINISHED, max_bytes=1, max_duration_s=1
        ).id.hex
        for robot_id in ("alice-bot", "alice-spare", "bob-bot")
    }
    release = Release.objects.create(
        organization=personal_organization(users["owner"]), skill_id="people-counting", number=1, config={}
    )
    rollout = Rollout.objects.create(
        organization=release.organization, release=release, selector="site=lab", state=Rollout.State.ROLLED_BACK
    )
    return World(daphne_server, tokens, robot_token, template.pk, recordings, release.pk, rollout.pk)


def fill(value: Any, ids: dict[str, Any]) -> Any:
    """Put ids into a path or body template; a string that is just one placeholder takes the id's own type."""
    if isinstance(value, dict):
        return {key: fill(item, ids) for key, item in value.items()}
    if isinstance(value, str):
        if value.startswith("{") and value.endswith("}") and value[1:-1] in ids:
            return ids[value[1:-1]]
        return value.format(**ids)
    return value


def call(world: World, route: Route, role: str, token: str | None, robot_id: str) -> httpx.Response:
    ids = {
        "robot_id": robot_id,
        "skill_id": SKILL,
        "component_id": "sampler",
        "template_id": world.template_id,
        "recording_id": world.recordings[robot_id],
        "role": role,
        "new_config": new_template_config(),
        # alice's personal organization, alice herself in it, and a token nobody has.
        "slug": "alice",
        "username": "alice",
        "token_id": 999999,
        "release_id": world.release_id,
        "rollout_id": world.rollout_id,
    }
    with client(world.server, token) as http:
        return http.request(route.method, fill(route.path, ids), json=fill(route.body, ids))


def snapshot() -> list:
    """Return everything a request could write, to prove a refused one wrote nothing."""
    return [
        list(Robot.objects.order_by("id").values_list("id", "name", "token_hash", "config")),
        list(Skill.objects.order_by("id").values_list("robot_id", "skill_id", "status", "config")),
        list(Component.objects.order_by("id").values_list("component_id", "status", "active_location")),
        list(SkillTemplate.objects.order_by("id").values_list("id", "name")),
        list(Recording.objects.order_by("id").values_list("id", "status")),
        BridgeTicket.objects.count(),
    ]


def route_id(route: Route) -> str:
    return f"{route.method} {route.path} {route.body or ''}".strip()


@pytest.mark.parametrize("route", ROUTES, ids=route_id)
def test_each_route_answers_each_caller_as_its_rights_say(world, route):
    callers = [
        ("anonymous", None, "alice-bot", route.anonymous),
        # A robot's token never opens the user API, not even a public route: it is refused, not ignored.
        ("robot", world.robot_token, "alice-bot", route.robot),
        ("other", world.tokens["other"], "alice-bot", route.other),
        ("owner", world.tokens["owner"], "alice-bot", route.owner),
        ("staff", world.tokens["staff"], "alice-spare", route.staff),
    ]
    for role, token, robot_id, expected in callers:
        before = snapshot()
        response = call(world, route, role, token, robot_id)
        assert response.status_code == expected, f"{role}: {response.status_code} {response.text[:300]}"
        if expected in REFUSED:
            assert snapshot() == before, f"{role} was refused but something was written"
        if route.lists and expected == 200:
            text = response.text
            if role == "other":
                assert "alice" not in text and "bob-bot" in text, text[:500]
            elif role == "owner":
                assert "alice-bot" in text and "bob-bot" not in text, text[:500]
            elif role == "staff":
                assert "alice-bot" in text and "bob-bot" in text, text[:500]


def test_the_matrix_covers_every_route_of_the_schema():
    schema = SchemaGenerator().get_schema(request=None, public=True)
    published = {(method.upper(), path) for path, operations in schema["paths"].items() for method in operations}
    assert published == {(route.method, route.path) for route in ROUTES}


def test_another_users_robot_is_not_found_exactly_like_a_missing_one(world):
    with client(world.server, world.tokens["other"]) as http:
        theirs = http.get("/api/robot/alice-bot/info")
        missing = http.get("/api/robot/no-such-bot/info")
    assert theirs.status_code == missing.status_code == 404
    # At most the answer echoes the id asked about; it tells nothing more about a robot that exists.
    assert theirs.text.replace("alice-bot", "?") == missing.text.replace("no-such-bot", "?")


# --------------------------------------------------------------------------- /api/auth with a password


def basic(username: str, password: str) -> dict[str, str]:
    return {"Authorization": "Basic " + base64.b64encode(f"{username}:{password}".encode()).decode()}


@pytest.mark.parametrize("method", ["GET", "POST"])
def test_basic_credentials_get_a_token_that_expires_after_the_lifetime(daphne_server, method):
    user_with_token("alice", password=True)
    asked_at = timezone.now()
    with client(daphne_server) as http:
        response = http.request(method, "/api/auth", headers=basic("alice", "alice-pass-123"))
        assert response.status_code == 200, response.text
        answer = response.json()
        assert answer["token"].startswith("bat_")
        expires_at = ApiToken.objects.get(key_hash=hash_token(answer["token"])).expires_at
        assert abs(expires_at - (asked_at + timedelta(days=1))) < timedelta(seconds=30)
        assert answer["expires_at"].startswith(expires_at.strftime("%Y-%m-%dT%H:%M"))
        robots = http.get("/api/robot", headers={"Authorization": f"Token {answer['token']}"})
    assert robots.status_code == 200


@pytest.mark.parametrize("password", ["wrong-password", ""])
def test_a_wrong_password_gets_no_token(daphne_server, password):
    user_with_token("alice", password=True)
    with client(daphne_server) as http:
        response = http.get("/api/auth", headers=basic("alice", password))
    assert response.status_code == 401
    assert "token" not in response.json()
    assert ApiToken.objects.count() == 1


def test_an_unknown_user_gets_no_token(daphne_server):
    with client(daphne_server) as http:
        assert http.post("/api/auth", headers=basic("nobody", "nobody-pass-123")).status_code == 401
        # PostgreSQL refuses a NUL byte outright; it once made this a 500.
        assert http.post("/api/auth", headers=basic("no\x00body", "pass")).status_code == 401


def test_renewing_pushes_the_expiry_a_full_lifetime_ahead(daphne_server):
    user, key = user_with_token("alice")
    ApiToken.objects.filter(user=user).update(expires_at=timezone.now() + timedelta(minutes=1))
    with client(daphne_server, key) as http:
        response = http.post("/api/auth/renew")
    assert response.status_code == 200, response.text
    expires_at = ApiToken.objects.get(user=user).expires_at
    assert abs(expires_at - (timezone.now() + timedelta(days=1))) < timedelta(seconds=30)
    assert response.json()["expires_at"].startswith(expires_at.strftime("%Y-%m-%dT%H:%M"))


def test_an_expired_token_is_refused_everywhere_even_for_renewal(daphne_server):
    user, key = user_with_token("alice")
    ApiToken.objects.filter(user=user).update(expires_at=timezone.now() - timedelta(seconds=1))
    with client(daphne_server, key) as http:
        assert http.get("/api/robot").status_code == 401
        assert http.post("/api/auth/renew").status_code == 401
        assert http.get("/api/events").status_code == 401


def test_a_deactivated_users_token_is_refused(daphne_server):
    user, key = user_with_token("alice")
    get_user_model().objects.filter(pk=user.pk).update(is_active=False)
    with client(daphne_server, key) as http:
        assert http.get("/api/robot").status_code == 401


def test_a_made_up_token_is_refused(daphne_server):
    with client(daphne_server, "bat_not-a-real-token") as http:
        assert http.get("/api/robot").status_code == 401


def test_api_auth_only_answers_get_and_post(daphne_server):
    user_with_token("alice", password=True)
    with client(daphne_server) as http:
        assert http.delete("/api/auth", headers=basic("alice", "alice-pass-123")).status_code == 405
