"""One audit entry per action per door: the Robot API, logins, the admin, the client WebSocket, bridges, the registry."""

from __future__ import annotations

import asyncio
import base64
from datetime import UTC, datetime
from typing import Any

import httpx
import pytest
from django.contrib.auth import get_user_model
from django.core.management import call_command
from django.test import Client
from websockets.sync.client import connect

from audit.models import AuditEntry
from bridgeos_agent.protocol import Event
from registry.notifications import TagPush
from registry.services import record_pushes
from robots.services import issue_api_token
from teams.services import personal_organization
from tests.cloud.apiutil import SKILL, client, robot_of, user_with_token
from tests.cloud.wsutil import client_link
from tests.conftest import wait_until

pytestmark = pytest.mark.django_db(transaction=True)


def only(**match: Any) -> AuditEntry:
    """Return the one entry matching, failing if there are none or several."""
    found = list(AuditEntry.objects.filter(**match))
    assert len(found) == 1, f"{len(found)} entries match {match}: {[str(entry) for entry in found]}"
    return found[0]


@pytest.fixture
def alice(daphne_server) -> tuple[Any, str]:
    """Alice, admin of her personal organization, owner of alice-bot, with a named API token."""
    user, _ = user_with_token("alice", password=True)
    robot_of(user, "alice-bot")
    key, _ = issue_api_token(user, name="laptop")
    return user, key


def test_each_robot_api_write_is_one_entry_with_who_what_object_and_outcome(daphne_server, alice):
    user, key = alice
    personal = personal_organization(user)
    skill = f"/api/robot/alice-bot/skill/{SKILL}"
    with client(daphne_server, key) as http:
        assert http.get("/api/robot").status_code == 200  # a read: not audited
        assert http.post("/api/robot", json={"id": "new-bot"}).status_code == 201
        assert http.patch("/api/robot/new-bot", json={"name": "Kitchen"}).status_code == 200
        started = http.post(f"{skill}/start").status_code
        stopped = http.post(f"{skill}/stop").status_code
        migrated = http.post(f"{skill}/component/sampler/migrate", json={}).status_code
        assert http.delete("/api/robot/new-bot").status_code == 204
        assert http.delete("/api/robot/new-bot").status_code == 404
    entries = list(AuditEntry.objects.order_by("id"))
    assert [(entry.action, entry.object, entry.status) for entry in entries] == [
        ("robot.create", "robot/new-bot", 201),
        ("robot.update", "robot/new-bot", 200),
        ("skill.start", f"robot/alice-bot/skill/{SKILL}", started),
        ("skill.stop", f"robot/alice-bot/skill/{SKILL}", stopped),
        ("component.migrate", f"robot/alice-bot/skill/{SKILL}/component/sampler", migrated),
        ("robot.delete", "robot/new-bot", 204),
        ("robot.delete", "robot/new-bot", 404),
    ]
    for entry in entries:
        assert (entry.actor, entry.token, entry.door, entry.address) == ("alice", "laptop", "rest", "127.0.0.1")
    # The deleted robot's organization is known from before the deletion; the second delete found no robot.
    assert [entry.organization_slug for entry in entries[:6]] == [personal.slug] * 6
    assert entries[5].outcome == "ok" and entries[6].outcome == "not_found"
    assert entries[0].data == {"method": "POST", "path": "/api/robot"}


def test_another_users_attempt_is_written_as_refused(daphne_server, alice):
    _, bob_key = user_with_token("bob")
    with client(daphne_server, bob_key) as http:
        assert http.delete("/api/robot/alice-bot").status_code == 404
    with client(daphne_server, "bat_forged") as http:
        assert http.post("/api/robot", json={"id": "x-bot"}).status_code == 401
    assert only(actor="bob").outcome == "not_found"
    assert only(action="robot.create").outcome == "denied"


def test_a_token_from_api_auth_and_a_wrong_password_are_one_entry_each(daphne_server, alice):
    basic = "Basic " + base64.b64encode(b"alice:alice-pass-123").decode()
    wrong = "Basic " + base64.b64encode(b"alice:nope").decode()
    assert httpx.post(f"{daphne_server.url}/api/auth", headers={"Authorization": basic}).status_code == 200
    assert httpx.post(f"{daphne_server.url}/api/auth", headers={"Authorization": wrong}).status_code == 401
    issued = only(action="token.issue")
    assert (issued.actor, issued.door, issued.outcome) == ("alice", "rest", "ok")
    failed = only(action="login.failed")
    assert (failed.actor, failed.door, failed.status, failed.outcome) == ("alice", "rest", 401, "denied")
    assert AuditEntry.objects.count() == 2


def test_dashboard_and_admin_logins_and_an_admin_change_are_one_entry_each(daphne_server):
    get_user_model().objects.create_user("root", password="root-pass-123", is_staff=True, is_superuser=True)
    browser = Client()
    assert browser.post("/accounts/login/", {"username": "root", "password": "wrong"}).status_code == 200
    assert browser.post("/accounts/login/", {"username": "root", "password": "root-pass-123"}).status_code == 302
    assert browser.post("/admin/login/", {"username": "root", "password": "wrong"}).status_code == 200
    assert browser.post("/admin/auth/group/add/", {"name": "operators"}).status_code == 302
    assert browser.post("/admin/auth/group/add/", {"name": ""}).status_code == 200  # the form again, with errors
    assert [(entry.door, entry.action, entry.actor, entry.outcome) for entry in AuditEntry.objects.order_by("id")] == [
        ("login", "login.failed", "root", "denied"),
        ("login", "login", "root", "ok"),
        ("admin", "login.failed", "root", "denied"),
        ("admin", "admin.auth_group_add", "root", "ok"),
        ("admin", "admin.auth_group_add", "root", "invalid"),
    ]


async def test_every_command_is_written_although_its_client_leaves_at_once(daphne_server, alice):
    from asgiref.sync import sync_to_async

    _, key = alice
    link = await client_link(daphne_server, key)
    commands = 15  # within the per-robot command limit
    answers = await asyncio.gather(*(link.request(Event.ROBOT_STOP, {"robot": "alice-bot"}) for _ in range(commands)))
    assert [answer.data["code"] for answer in answers] == ["robot_offline"] * commands
    # At once: the last commands' entries still wait for daphne's database thread, and leaving
    # cancels what the connection was doing. Their writes were cancelled with it, and lost.
    await link.close()
    await sync_to_async(wait_until)(
        lambda: AuditEntry.objects.filter(door="ws").count() >= commands,
        what=f"{commands} entries",
    )
    assert await sync_to_async(AuditEntry.objects.filter(door="ws").count)() == commands


async def test_a_client_websocket_command_is_one_entry(daphne_server, alice):
    from asgiref.sync import sync_to_async

    _, key = alice
    link = await client_link(daphne_server, key)
    answer = await link.request(Event.ROBOT_STOP, {"robot": "alice-bot"})
    assert answer.data["code"] == "robot_offline"
    await link.request(Event.ROBOT_STOP, {"robot": "nobody-bot"})
    await link.close()
    await sync_to_async(wait_until)(lambda: AuditEntry.objects.filter(door="ws").count() == 2)
    entries = await sync_to_async(lambda: list(AuditEntry.objects.filter(door="ws").order_by("id")))()
    assert [(entry.action, entry.object, entry.actor, entry.token, entry.outcome) for entry in entries] == [
        (f"ws.{Event.ROBOT_STOP.value}", "robot/alice-bot", "alice", "laptop", "failed"),
        (f"ws.{Event.ROBOT_STOP.value}", "robot/nobody-bot", "alice", "laptop", "not_found"),
    ]


def test_a_bridge_session_opened_and_one_refused_are_one_entry_each(daphne_server, alice):
    _, key = alice
    address = f"{daphne_server.ws_url}/ws/rosbridge/alice-bot/"
    with connect(address, additional_headers={"Authorization": f"Token {key}"}, open_timeout=10) as websocket:
        websocket.recv(timeout=10)  # the robot is offline: told so, then closed
    with pytest.raises(Exception, match="403"):
        connect(address, additional_headers={"Authorization": "Token bat_forged"}, open_timeout=10).close()
    opened = only(action="bridge.open", outcome="ok")
    assert (opened.actor, opened.door, opened.object, opened.data) == (
        "alice",
        "bridge",
        "robot/alice-bot",
        {"kind": "rosbridge"},
    )
    assert only(action="bridge.open", outcome="denied").actor == ""


def test_each_registry_push_is_one_entry_by_its_pusher(db):
    user = get_user_model().objects.create_user("dave")
    slug = personal_organization(user).slug
    at = datetime.now(UTC)
    pushes = [
        TagPush(f"{slug}/detector", tag, "sha256:" + "a" * 64, "application/json", 10, "dave", at) for tag in ("1", "2")
    ]
    assert record_pushes(pushes) == 2
    entries = AuditEntry.objects.filter(action="registry.push").order_by("id")
    assert [entry.object for entry in entries] == [f"image/{slug}/detector:1", f"image/{slug}/detector:2"]
    assert {entry.actor for entry in entries} == {"dave"}
    assert {entry.organization_slug for entry in entries} == {slug}


def test_the_chain_written_through_the_doors_verifies(daphne_server, alice, capsys):
    with client(daphne_server, alice[1]) as http:
        for index in range(5):
            http.post("/api/robot", json={"id": f"bot-{index}"})
    call_command("audit", "verify")
    assert "5 entries verified" in capsys.readouterr().out


def test_member_changes_name_the_member_and_role_at_the_api_and_the_dashboard(daphne_server, alice):
    user, key = alice
    slug = personal_organization(user).slug
    for name in ("bob", "carol"):
        get_user_model().objects.create_user(name)
    with client(daphne_server, key) as http:
        assert http.post(f"/api/organizations/{slug}/members", json={"username": "bob", "role": "viewer"}).status_code
        assert http.patch(f"/api/organizations/{slug}/members/bob", json={"role": "operator"}).status_code == 200
        assert http.delete(f"/api/organizations/{slug}/members/bob").status_code == 204
        assert http.post("/api/database/query", json={"robot": "alice-bot"}).status_code in (200, 400)  # a read
    browser = Client()
    browser.force_login(user)
    assert browser.post(f"/organizations/{slug}/", {"username": "carol", "role": "developer"}).status_code == 302
    assert browser.post(f"/organizations/{slug}/members/carol", {"role": "admin"}).status_code == 302
    assert browser.post(f"/organizations/{slug}/members/carol", {"action": "remove"}).status_code == 302
    entries = list(AuditEntry.objects.filter(action__startswith="member.").order_by("id"))
    assert [(e.door, e.action, e.object, e.data.get("role"), e.outcome) for e in entries] == [
        ("rest", "member.add", f"organization/{slug}/member/bob", "viewer", "ok"),
        ("rest", "member.role", f"organization/{slug}/member/bob", "operator", "ok"),
        ("rest", "member.remove", f"organization/{slug}/member/bob", None, "ok"),
        ("dashboard", "member.add", f"organization/{slug}/member/carol", "developer", "ok"),
        ("dashboard", "member.role", f"organization/{slug}/member/carol", "admin", "ok"),
        ("dashboard", "member.remove", f"organization/{slug}/member/carol", None, "ok"),
    ]
    assert {e.organization_slug for e in entries} == {slug}
    assert not AuditEntry.objects.filter(action__startswith="database").exists()
