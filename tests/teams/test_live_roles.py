"""A live /ws/client/ follows its user's memberships: a role changed, added or ended applies without reconnecting."""

from __future__ import annotations

import asyncio
import importlib
import time

import httpx
import pytest
from asgiref.sync import sync_to_async
from django.conf import settings
from django.contrib.auth import BACKEND_SESSION_KEY, HASH_SESSION_KEY, SESSION_KEY, get_user_model

from bridgeos_agent.link import Link
from bridgeos_agent.protocol import Envelope, Event
from robots.access import SESSION_ORGANIZATION
from teams.models import Membership, Organization

from .teamutil import headers, login_token, robot_in, team, user

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.asyncio]

OFFLINE = {"code": "robot_offline", "field": "data.robot", "message": "robot lab-bot is offline"}
FORBIDDEN = {
    "code": "forbidden",
    "field": "event",
    "message": "robot_start needs the operator role in the robot's organization",
}
NOT_FOUND = {"code": "not_found", "field": "data.robot", "message": "no robot 'lab-bot'"}


@sync_to_async
def lab(**members: str) -> str:
    """Make the lab with ada as admin, members in roles, and its robot lab-bot (offline); return ada's login token."""
    organization = team("lab", ada="admin", **members)
    robot_in(organization, "lab-bot")
    return login_token(organization.memberships.get(user__username="ada").user)


@sync_to_async
def session_cookie(username: str, organization: str | None = None) -> str:
    """Log a user in to the dashboard (in an organization they picked, if given); return the session cookie."""
    found = get_user_model().objects.filter(username=username).first() or user(username)
    session = importlib.import_module(settings.SESSION_ENGINE).SessionStore()
    session[SESSION_KEY] = str(found.pk)
    session[BACKEND_SESSION_KEY] = "django.contrib.auth.backends.ModelBackend"
    session[HASH_SESSION_KEY] = found.get_session_auth_hash()
    if organization is not None:
        session[SESSION_ORGANIZATION] = Organization.objects.get(slug=organization).pk
    session.create()
    return f"{settings.SESSION_COOKIE_NAME}={session.session_key}"


async def open_session(server, cookie: str) -> Link:
    """Open /ws/client/ with the dashboard's session over a real socket."""
    link = Link(server.ws_url + "/ws/client/")
    await link.connect(Event.AUTHENTICATION_CLIENT, {}, headers={"Cookie": cookie})
    return link


async def open_token(server, key: str) -> Link:
    """Open /ws/client/ with an API token over a real socket."""
    link = Link(server.ws_url + "/ws/client/")
    await link.connect(Event.AUTHENTICATION_CLIENT, {"token": key})
    return link


async def start_lab_bot(link: Link) -> dict:
    """Ask to start lab-bot; return the error's data (offline: the role check let it through)."""
    answer: Envelope = await link.request(Event.ROBOT_START, {"robot": "lab-bot"})
    assert answer.event == Event.ERROR_MESSAGE, answer
    return dict(answer.data)


async def answered_within(link: Link, expected: dict, seconds: float = 1.0) -> float:
    """Ask until the answer is the expected one; fail unless it came within ``seconds``; return how long it took."""
    started = time.monotonic()
    while (got := await start_lab_bot(link)) != expected:
        assert time.monotonic() - started < seconds, f"still {got} after {seconds} s"
        await asyncio.sleep(0.02)
    took = time.monotonic() - started
    assert took < seconds
    return took


async def member_change(server, admin_key: str, method: str, path: str, **body) -> int:
    """Change a member of the lab through the Robot API as its admin; return the status code."""
    async with httpx.AsyncClient(base_url=server.url + "/api", headers=headers(admin_key)) as http:
        answer = await http.request(method, f"/organizations/lab/members{path}", json=body or None)
    return answer.status_code


async def closed_with(link: Link) -> int | None:
    """Wait for the cloud to close a link; return the close code."""
    await asyncio.wait_for(link.closed.wait(), 5)
    return link.close_code


async def test_a_demoted_operators_live_session_is_refused_commands_without_reconnecting(daphne_server):
    ada = await lab(bob="operator")
    link = await open_session(daphne_server, await session_cookie("bob", "lab"))
    assert await start_lab_bot(link) == OFFLINE
    assert await member_change(daphne_server, ada, "PATCH", "/bob", role="viewer") == 200
    await answered_within(link, FORBIDDEN)
    # Still the same socket, still reading the lab.
    answer = await link.request(Event.ROBOT_CONFIG_GET, {"robot": "lab-bot"})
    assert answer.event == Event.ROBOT_CONFIG
    assert answer.data["robot"] == "lab-bot"
    assert not link.closed.is_set()
    await link.close()


async def test_a_promoted_viewers_live_session_may_command_at_once(daphne_server):
    ada = await lab(vic="viewer")
    link = await open_session(daphne_server, await session_cookie("vic"))
    assert await start_lab_bot(link) == FORBIDDEN
    assert await member_change(daphne_server, ada, "PATCH", "/vic", role="operator") == 200
    await answered_within(link, OFFLINE)
    await link.close()


async def test_a_promotion_reaches_a_login_tokens_live_connection(daphne_server):
    ada = await lab(vic="viewer")
    vic = await sync_to_async(lambda: login_token(get_user_model().objects.get(username="vic")))()
    link = await open_token(daphne_server, vic)
    assert await start_lab_bot(link) == FORBIDDEN
    assert await member_change(daphne_server, ada, "PATCH", "/vic", role="operator") == 200
    await answered_within(link, OFFLINE)
    await link.close()


async def test_a_member_added_to_the_lab_reaches_its_robot_live(daphne_server):
    ada = await lab()
    link = await open_session(daphne_server, await session_cookie("bob"))
    assert await start_lab_bot(link) == NOT_FOUND
    assert await member_change(daphne_server, ada, "POST", "", username="bob", role="operator") == 201
    await answered_within(link, OFFLINE)
    await link.close()


async def test_removal_closes_a_session_held_to_the_lab(daphne_server):
    ada = await lab(bob="operator")
    link = await open_session(daphne_server, await session_cookie("bob", "lab"))
    assert await start_lab_bot(link) == OFFLINE
    assert await member_change(daphne_server, ada, "DELETE", "/bob") == 204
    assert await closed_with(link) == 4001


async def test_removal_hides_the_lab_from_a_session_of_all_the_users_organizations(daphne_server):
    ada = await lab(bob="operator")
    link = await open_session(daphne_server, await session_cookie("bob"))
    assert await start_lab_bot(link) == OFFLINE
    assert await member_change(daphne_server, ada, "DELETE", "/bob") == 204
    # Bob's own organization stays his: the socket stays open, and the lab's robot is as if it did not exist.
    await answered_within(link, NOT_FOUND)
    answer = await link.request(Event.ROBOT_CONFIG_GET, {"robot": "lab-bot"})
    assert dict(answer.data) == NOT_FOUND
    assert not link.closed.is_set()
    await link.close()


async def test_a_role_changed_outside_the_api_applies_live_too(daphne_server):
    # The Django admin and any other door save the membership: the change reaches the socket the same way.
    await lab(bob="operator")
    link = await open_session(daphne_server, await session_cookie("bob", "lab"))
    assert await start_lab_bot(link) == OFFLINE
    membership = await sync_to_async(Membership.objects.get)(user__username="bob", organization__slug="lab")
    membership.role = "viewer"
    await sync_to_async(membership.save)()
    await answered_within(link, FORBIDDEN)
    await sync_to_async(membership.delete)()
    assert await closed_with(link) == 4001


async def test_deactivating_a_user_closes_their_live_connections(daphne_server):
    await lab(bob="operator")
    bob = await sync_to_async(get_user_model().objects.get)(username="bob")
    by_session = await open_session(daphne_server, await session_cookie("bob"))
    by_token = await open_token(daphne_server, await sync_to_async(login_token)(bob))
    bob.is_active = False
    await sync_to_async(bob.save)()
    assert await closed_with(by_session) == 4001
    assert await closed_with(by_token) == 4001


async def test_deleting_a_user_closes_their_live_connections(daphne_server):
    await lab(bob="operator")
    link = await open_session(daphne_server, await session_cookie("bob"))
    assert await start_lab_bot(link) == OFFLINE
    await sync_to_async(get_user_model().objects.filter(username="bob").delete)()
    assert await closed_with(link) == 4001


async def test_another_users_change_leaves_a_connection_as_it_was(daphne_server):
    ada = await lab(bob="operator", vic="operator")
    link = await open_session(daphne_server, await session_cookie("bob", "lab"))
    assert await member_change(daphne_server, ada, "PATCH", "/vic", role="viewer") == 200
    await asyncio.sleep(0.5)
    assert await start_lab_bot(link) == OFFLINE
    assert not link.closed.is_set()
    await link.close()
