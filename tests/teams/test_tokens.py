"""Scoped API tokens: held to one organization and a role, expiring, and revoked mid-session (live sockets closed)."""

from __future__ import annotations

import asyncio
from datetime import timedelta

import httpx
import pytest
from asgiref.sync import sync_to_async
from django.utils import timezone

from bridgeos_agent.link import Link
from bridgeos_agent.protocol import Event
from robots.models import ApiToken
from robots.services import create_robot, issue_api_token
from teams.models import Organization

from .teamutil import headers, login_token, robot_in, team, user

pytestmark = pytest.mark.django_db(transaction=True)


def api(server, token: str) -> httpx.Client:
    """Return an HTTP client of the Robot API sending a token."""
    return httpx.Client(base_url=server.url + "/api", headers=headers(token), timeout=15)


def make_token(server, login: str, **body) -> dict:
    """Make a scoped token through the API and return the answer (with its key)."""
    with api(server, login) as http:
        answer = http.post("/tokens", json=body)
    assert answer.status_code == 201, answer.text
    return answer.json()


def test_a_viewer_token_reads_but_may_not_command(daphne_server):
    lab = team("lab", ada="admin")
    robot_in(lab, "lab-bot")
    ada = lab.memberships.get().user
    viewer = make_token(daphne_server, login_token(ada), name="grafana", organization="lab", role="viewer")
    assert viewer["role"] == "viewer"
    assert viewer["expires_at"] is None
    with api(daphne_server, viewer["key"]) as http:
        assert http.get("/robot/lab-bot").status_code == 200
        start = http.post("/robot/lab-bot/start")
        assert start.status_code == 403
        assert "operator role" in start.json()["detail"]
        assert "your role here is viewer" in start.json()["detail"]


def test_a_token_reaches_only_its_organization(daphne_server):
    lab = team("lab", ada="admin")
    ada = lab.memberships.get().user
    robot_in(lab, "lab-bot")
    create_robot("home-bot", ada)  # in ada's personal organization, where she is admin too
    operator = make_token(daphne_server, login_token(ada), name="ci", organization="lab", role="operator")
    with api(daphne_server, operator["key"]) as http:
        assert [r["id"] for r in http.get("/robot").json()] == ["lab-bot"]
        other, missing = http.get("/robot/home-bot"), http.get("/robot/no-bot")
        assert other.status_code == missing.status_code == 404
        assert other.content == missing.content
        assert http.post("/robot/home-bot/start").status_code == 404
        assert [o["slug"] for o in http.get("/organizations").json()] == ["lab"]
        # Offline, so the command is refused by the robot's absence, not by the role.
        assert http.post("/robot/lab-bot/start").status_code == 409


def test_a_token_role_above_the_users_is_refused(daphne_server):
    lab = team("lab", ada="admin", bob="operator")
    bob = lab.memberships.get(user__username="bob").user
    before = ApiToken.objects.count()
    with api(daphne_server, login_token(bob)) as http:
        answer = http.post("/tokens", json={"name": "x", "organization": "lab", "role": "developer"})
        assert answer.status_code == 400
        assert answer.json() == {"role": ["A token's role may be at most yours here (operator)."]}
        foreign = http.post("/tokens", json={"name": "x", "organization": "ada", "role": "viewer"})
        missing = http.post("/tokens", json={"name": "x", "organization": "nope", "role": "viewer"})
        assert foreign.status_code == missing.status_code == 400
        assert foreign.content == missing.content
        past = http.post(
            "/tokens",
            json={"name": "x", "organization": "lab", "role": "viewer", "expires_at": "2001-01-01T00:00:00Z"},
        )
        assert past.json() == {"expires_at": ["Give an instant in the future."]}
        days = http.post("/tokens", json={"name": "x", "organization": "lab", "role": "viewer", "expires_in_days": 0})
        assert "expires_in_days" in days.json()
    assert ApiToken.objects.count() == before + 1  # only the login token


def test_a_token_with_a_cap_above_a_lowered_role_acts_with_the_role(daphne_server):
    lab = team("lab", ada="admin", bob="operator")
    robot_in(lab, "lab-bot")
    bob = lab.memberships.get(user__username="bob").user
    operator = make_token(daphne_server, login_token(bob), name="ops", organization="lab", role="operator")
    with api(daphne_server, login_token(lab.memberships.get(role="admin").user)) as http:
        assert http.patch("/organizations/lab/members/bob", json={"role": "viewer"}).status_code == 200
    assert ApiToken.objects.get(pk=operator["id"]).role == "viewer"
    with api(daphne_server, operator["key"]) as http:
        assert http.post("/robot/lab-bot/start").status_code == 403
        assert http.get("/robot/lab-bot").status_code == 200


def test_an_expired_token_is_refused(daphne_server):
    lab = team("lab", ada="admin")
    ada = lab.memberships.get().user
    key, _ = issue_api_token(ada, name="old", organization=lab, role="viewer", expires_at=timezone.now())
    soon = make_token(
        daphne_server, login_token(ada), name="soon", organization="lab", role="viewer", expires_in_days=2
    )
    assert (
        timedelta(days=1) < (timezone.datetime.fromisoformat(soon["expires_at"]) - timezone.now()) <= timedelta(days=2)
    )
    with api(daphne_server, key) as http:
        assert http.get("/robot").status_code == 401


def test_tokens_are_listed_without_keys_and_revoked(daphne_server):
    lab = team("lab", ada="admin", bob="operator")
    ada, bob = (lab.memberships.get(user__username=name).user for name in ("ada", "bob"))
    bob_login = login_token(bob)
    made = make_token(daphne_server, bob_login, name="robot-ci", organization="lab", role="operator")
    with api(daphne_server, bob_login) as http:
        mine = http.get("/tokens").json()
        assert {t["name"] for t in mine} == {"", "robot-ci"}  # the login token too
        assert all("key" not in t for t in mine)
        assert next(t for t in mine if t["name"] == "robot-ci")["organization"] == "lab"
    with api(daphne_server, login_token(user("eve"))) as http:
        assert http.delete(f"/tokens/{made['id']}").status_code == 404
    with api(daphne_server, login_token(ada)) as http:
        listed = http.get("/organizations/lab/tokens").json()
        assert [(t["name"], t["user"]) for t in listed] == [("robot-ci", "bob")]
        # An admin of the organization revokes a member's token.
        assert http.delete(f"/tokens/{made['id']}").status_code == 204
        assert http.delete(f"/tokens/{made['id']}").status_code == 404
    with api(daphne_server, made["key"]) as http:
        assert http.get("/robot").status_code == 401


# --------------------------------------------------------------------------- live connections


async def open_client(server, key: str) -> Link:
    """Open /ws/client/ with an API token over a real socket."""
    link = Link(server.ws_url + "/ws/client/")
    await link.connect(Event.AUTHENTICATION_CLIENT, {"token": key})
    return link


async def closed_with(link: Link) -> int | None:
    """Wait for the cloud to close a link; return the close code."""
    await asyncio.wait_for(link.closed.wait(), 10)
    return link.ws.close_code


@sync_to_async
def lab_with_members() -> tuple[str, str, str]:
    """Make a lab with an admin and an operator; return their login tokens and the operator's scoped token."""
    lab = team("lab", ada="admin", bob="operator")
    ada, bob = (lab.memberships.get(user__username=name).user for name in ("ada", "bob"))
    key, _ = issue_api_token(bob, name="live", organization=lab, role="operator", expires_at=None)
    return login_token(ada), login_token(bob), key


async def test_revoking_a_token_closes_its_live_connection(daphne_server):
    _, bob_login, key = await lab_with_members()
    revoked, kept = await open_client(daphne_server, key), await open_client(daphne_server, bob_login)
    token_id = await sync_to_async(lambda: ApiToken.objects.get(name="live").pk)()
    async with httpx.AsyncClient(base_url=daphne_server.url, headers=headers(bob_login)) as http:
        assert (await http.delete(f"/api/tokens/{token_id}")).status_code == 204
    assert await closed_with(revoked) == 4001
    # Another token of the same user stays connected.
    assert not kept.closed.is_set()
    await kept.close()


async def test_removing_a_member_closes_their_tokens_live_connections(daphne_server):
    ada_login, bob_login, key = await lab_with_members()
    link = await open_client(daphne_server, key)
    # A login token's connection loaded bob's roles too: it closes, and reopens without the lab.
    login_link = await open_client(daphne_server, bob_login)
    async with httpx.AsyncClient(base_url=daphne_server.url, headers=headers(ada_login)) as http:
        assert (await http.delete("/api/organizations/lab/members/bob")).status_code == 204
    assert await closed_with(link) == 4001
    assert await closed_with(login_link) == 4001
    assert not await sync_to_async(ApiToken.objects.filter(name="live").exists)()
    with pytest.raises(Exception, match="invalid token"):
        await open_client(daphne_server, key)


async def test_lowering_a_members_role_reopens_their_tokens_connections(daphne_server):
    ada_login, _, key = await lab_with_members()
    link = await open_client(daphne_server, key)
    async with httpx.AsyncClient(base_url=daphne_server.url, headers=headers(ada_login)) as http:
        assert (await http.patch("/api/organizations/lab/members/bob", json={"role": "viewer"})).status_code == 200
    assert await closed_with(link) == 4001
    # The token still works, now as a viewer.
    again = await open_client(daphne_server, key)
    await again.close()
    assert await sync_to_async(lambda: Organization.objects.get(slug="lab").api_tokens.get().role)() == "viewer"


def test_a_scoped_token_lists_and_revokes_only_its_organizations_tokens(daphne_server):
    lab = team("lab", ada="admin")
    ada = lab.memberships.get().user
    login = login_token(ada)
    scoped = make_token(daphne_server, login, name="lab-ci", organization="lab", role="admin")
    home = make_token(daphne_server, login, name="home-ci", organization="ada", role="admin")
    with api(daphne_server, scoped["key"]) as http:
        assert [t["name"] for t in http.get("/tokens").json()] == ["lab-ci"]
        assert http.delete(f"/tokens/{home['id']}").status_code == 404
    assert ApiToken.objects.filter(pk=home["id"]).exists()
