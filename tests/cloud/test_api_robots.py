"""The Robot API on robots, Skills and components, against daphne, PostgreSQL and connected reference robots."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import httpx
import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.link import AuthenticationError, Link
from bridgeos_agent.protocol import Event
from robots.models import Robot
from skills.models import Component, Skill, SkillTemplate
from skills.services import create_template

from .apiutil import (
    SKILL,
    async_client,
    client,
    make_owner,
    make_robot,
    robot_of,
    sample_skill_config,
    user_with_token,
)
from .test_api_auth import snapshot
from .wsutil import robot_link

pytestmark = pytest.mark.django_db(transaction=True)


@pytest.fixture
def alice(daphne_server) -> tuple[Any, str]:
    """Alice, owner of alice-bot (with the sample Skill), and her API token."""
    user, token = user_with_token("alice")
    robot_of(user, "alice-bot")
    return user, token


@pytest.fixture
def http(daphne_server, alice):
    with client(daphne_server, alice[1]) as http:
        yield http


@asynccontextmanager
async def connected(server: Any, robot_id: str, token: str, *, auto_ack: bool = True) -> AsyncIterator[Link]:
    """Connect a reference robot for the duration of a block."""
    link = await robot_link(server, robot_id, token)
    link.auto_ack = auto_ack
    try:
        yield link
    finally:
        await link.close()


@asynccontextmanager
async def alice_and_her_robot(server: Any, *, auto_ack: bool = True) -> AsyncIterator[tuple[Link, httpx.AsyncClient]]:
    """Create Alice and her robot, connect it and give Alice an API client, for the duration of a block."""
    alice, key = await make_owner("alice")
    token = await make_robot(alice, "alice-bot")
    async with connected(server, "alice-bot", token, auto_ack=auto_ack) as robot, async_client(server, key) as http:
        yield robot, http


# --------------------------------------------------------------------------- robots


async def test_a_new_robots_token_is_shown_once_and_connects_it(daphne_server):
    _, key = await make_owner("alice")
    async with async_client(daphne_server, key) as http:
        created = await http.post("/api/robot", json={"id": "new-bot", "name": "New bot"})
        assert created.status_code == 201, created.text
        body = created.json()
        assert body["id"] == "new-bot" and body["name"] == "New bot" and body["owner"] == "alice"
        assert body["skills"] == [] and body["connected"] is False
        assert body["config"]["offloading"] == "auto"
        shown_again = (await http.get("/api/robot/new-bot")).json()
        assert "token" not in shown_again
        assert "token" not in json.dumps(shown_again)
        async with connected(daphne_server, "new-bot", body["token"]):
            assert (await http.get("/api/robot/new-bot")).json()["connected"] is True


async def test_rotating_the_token_shuts_the_old_one_out_and_lets_the_new_one_in(daphne_server):
    alice, key = await make_owner("alice")
    old = await make_robot(alice, "alice-bot")
    async with async_client(daphne_server, key) as http:
        rotated = await http.post("/api/robot/alice-bot/token")
    assert rotated.status_code == 200
    new = rotated.json()["token"]
    assert new != old
    with pytest.raises(AuthenticationError):
        await robot_link(daphne_server, "alice-bot", old)
    async with connected(daphne_server, "alice-bot", new):
        pass


async def test_rotating_the_token_closes_the_connection_made_with_the_old_one(daphne_server):
    alice, key = await make_owner("alice")
    old = await make_robot(alice, "alice-bot")
    link = await robot_link(daphne_server, "alice-bot", old)
    async with async_client(daphne_server, key) as http:
        assert (await http.post("/api/robot/alice-bot/token")).status_code == 200
    await asyncio.wait_for(link.closed.wait(), 5)
    assert link.close_code == 4004


async def test_deleting_a_robot_closes_its_connection(daphne_server):
    alice, key = await make_owner("alice")
    link = await robot_link(daphne_server, "alice-bot", await make_robot(alice, "alice-bot"))
    async with async_client(daphne_server, key) as http:
        assert (await http.delete("/api/robot/alice-bot")).status_code == 204
    await asyncio.wait_for(link.closed.wait(), 5)
    assert link.close_code == 4004
    assert not await sync_to_async(Robot.objects.filter(id="alice-bot").exists)()


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"id": "alice-bot"}, "id"),
        ({"id": "start"}, "id"),
        ({"id": "Not A Slug"}, "id"),
        ({"id": "x" * 65}, "id"),
        ({}, "id"),
        ({"id": "new-bot", "config": {"offloading": "sideways"}}, "config"),
        ({"id": "new-bot", "config": {"threshold": "high"}}, "config"),
        ({"id": "new-bot", "config": []}, "config"),
        ({"id": "new-bot", "owner": "nobody"}, None),
    ],
)
def test_a_robot_that_cannot_be_created_leaves_nothing_behind(http, body, field):
    before = snapshot()
    response = http.post("/api/robot", json=body)
    assert response.status_code in (400, 403), response.text
    if field:
        assert response.status_code == 400 and field in response.json()
    assert snapshot() == before


def test_an_invalid_robot_config_names_the_bad_field(http):
    response = http.post("/api/robot", json={"id": "new-bot", "config": {"offloading": "sideways"}})
    assert response.status_code == 400
    [message] = response.json()["config"]
    assert message.startswith("offloading: ")


def test_only_staff_create_robots_for_another_user(daphne_server, alice):
    user_with_token("bob")
    _, staff = user_with_token("ops", staff=True)
    with client(daphne_server, alice[1]) as http:
        assert http.post("/api/robot", json={"id": "for-bob", "owner": "bob"}).status_code == 403
        assert http.post("/api/robot", json={"id": "own-bot", "owner": "alice"}).status_code == 201
    with client(daphne_server, staff) as http:
        made = http.post("/api/robot", json={"id": "for-bob", "owner": "bob"})
        assert made.status_code == 201 and made.json()["owner"] == "bob"
        assert http.post("/api/robot", json={"id": "for-ghost", "owner": "ghost"}).json() == {
            "owner": ["No such user."]
        }
    assert not Robot.objects.filter(id="for-ghost").exists()


def test_a_robot_is_renamed_and_reconfigured_and_a_bad_config_changes_nothing(http):
    renamed = http.patch("/api/robot/alice-bot", json={"name": "Kitchen", "config": {"offloading": "manual"}})
    assert renamed.status_code == 200, renamed.text
    assert renamed.json()["name"] == "Kitchen"
    assert renamed.json()["config"]["offloading"] == "manual"
    # The config is replaced as a whole; what is left out takes its default.
    assert renamed.json()["config"]["threshold"] == 0.5
    before = snapshot()
    refused = http.patch("/api/robot/alice-bot", json={"name": "Garage", "config": {"heartbeat_interval": -1}})
    assert refused.status_code == 400
    assert refused.json()["config"][0].startswith("heartbeat_interval: ")
    assert snapshot() == before


def test_deleting_a_robot_takes_its_skills_and_components_with_it(http):
    assert http.delete("/api/robot/alice-bot").status_code == 204
    assert http.get("/api/robot/alice-bot").status_code == 404
    assert not Skill.objects.exists() and not Component.objects.exists()
    assert http.delete("/api/robot/alice-bot").status_code == 404


def test_robot_info_shows_its_skills_and_components(http):
    info = http.get("/api/robot/alice-bot/info").json()
    assert set(info) == {
        "id",
        "name",
        "organization",
        "owner",
        "labels",
        "status",
        "connected",
        "last_seen",
        "ros_master",
        "ros2",
        "config",
        "skills",
    }
    [skill] = info["skills"]
    assert skill["skill_id"] == SKILL and skill["status"] == "stopped"
    components = {c["component_id"]: c for c in skill["components"]}
    assert set(components) == {"pointcloud", "sampler", "detector"}
    assert components["pointcloud"]["location"] == "robot"
    assert components["sampler"]["location"] == "either"
    assert components["detector"]["resources"]["cpu"] == 1.5
    assert http.get("/api/robot").json() == [info]


def test_the_fleet_can_be_filtered_by_connection(http):
    assert [r["id"] for r in http.get("/api/robot?connected=false").json()] == ["alice-bot"]
    assert http.get("/api/robot?connected=true").json() == []
    assert http.get("/api/robot?connected=maybe").status_code == 400


def test_skill_and_component_info_show_their_config(http):
    skill = http.get(f"/api/robot/alice-bot/skill/{SKILL}/info").json()
    assert skill["robot"] == "alice-bot" and skill["config"]["skill_id"] == SKILL
    component = http.get(f"/api/robot/alice-bot/skill/{SKILL}/component/detector/info").json()
    assert component["robot"] == "alice-bot" and component["skill"] == SKILL
    assert component["config"] == sample_skill_config()["components"]["detector"]


@pytest.mark.parametrize(
    "path",
    [
        "/api/robot/no-bot/info",
        "/api/robot/alice-bot/skill/no-skill/info",
        f"/api/robot/alice-bot/skill/{SKILL}/component/no-component/info",
        "/api/templates/999999",
    ],
)
def test_unknown_ids_are_not_found(http, path):
    assert http.get(path).status_code == 404


@pytest.mark.parametrize(
    "path",
    [
        "/api/robot/alice%00bot/info",
        "/api/robot/alice-bot/skill/people%00detection/info",
        f"/api/robot/alice-bot/skill/{SKILL}/component/sam%00pler/start",
        "/api/robot/Alice.Bot",
    ],
)
def test_an_id_no_robot_skill_or_component_could_have_is_not_found(http, path):
    # A NUL byte once reached PostgreSQL, which refuses it outright: a 500.
    assert http.post(path, json={"location": "robot"}).status_code in (404, 405)
    assert http.get(path).status_code in (404, 405)


# --------------------------------------------------------------------------- skills


def people_counting() -> dict[str, Any]:
    return {**sample_skill_config(), "skill_id": "people-counting", "skill": "People counting"}


def test_a_skill_is_added_from_a_config(http):
    added = http.post("/api/robot/alice-bot/skill/add", json={"config": people_counting()})
    assert added.status_code == 201, added.text
    assert added.json()["skill_id"] == "people-counting"
    assert len(added.json()["components"]) == 3
    assert Component.objects.filter(skill__skill_id="people-counting").count() == 3


def test_a_skill_is_added_from_a_catalog_template(http):
    template = create_template(name="People counting", config=people_counting())
    added = http.post("/api/robot/alice-bot/skill/add", json={"template": template.pk})
    assert added.status_code == 201, added.text
    assert added.json()["config"] == template.config


@pytest.mark.parametrize(
    ("body", "errors"),
    [
        (
            {
                "config": {
                    **people_counting(),
                    "components": {"sampler": {"location": "robot", "resources": {"cpu": -1}}},
                }
            },
            {"config"},
        ),
        ({"config": "not an object"}, {"config"}),
        ({"config": sample_skill_config()}, {"skill_id"}),
        ({"template": 999999}, {"template"}),
        ({}, {"non_field_errors"}),
        ({"config": people_counting(), "template": 1}, {"template"}),
    ],
)
def test_a_skill_that_cannot_be_added_is_refused_with_field_errors_and_nothing_written(http, body, errors):
    before = snapshot()
    response = http.post("/api/robot/alice-bot/skill/add", json=body)
    assert response.status_code == 400, response.text
    assert set(response.json()) <= errors | {"non_field_errors"} and set(response.json()) & errors
    assert snapshot() == before


def test_an_invalid_skill_config_names_each_bad_path_from_the_shared_schema(http):
    config = people_counting()
    config["components"]["sampler"]["resources"]["cpu"] = -1
    response = http.post("/api/robot/alice-bot/skill/add", json={"config": config})
    assert response.status_code == 400
    [message] = response.json()["config"]
    assert message.startswith("components.sampler.resources.cpu: ")


def test_a_stopped_skill_is_removed_and_a_running_one_is_not(http):
    Skill.objects.filter(skill_id=SKILL).update(status="running")
    before = snapshot()
    refused = http.post("/api/robot/alice-bot/skill/remove", json={"skill": SKILL})
    assert refused.status_code == 409
    assert snapshot() == before
    Skill.objects.filter(skill_id=SKILL).update(status="stopped")
    assert http.post("/api/robot/alice-bot/skill/remove", json={"skill": SKILL}).status_code == 204
    assert not Component.objects.exists()
    assert http.post("/api/robot/alice-bot/skill/remove", json={"skill": SKILL}).status_code == 404
    assert http.post("/api/robot/alice-bot/skill/remove", json={}).status_code == 400


# --------------------------------------------------------------------------- component location rules


COMPONENT = f"/api/robot/alice-bot/skill/{SKILL}/component"


def test_a_robot_only_component_cannot_start_or_move_to_the_cloud(http):
    started = http.post(f"{COMPONENT}/pointcloud/start", json={"location": "cloud"})
    assert started.status_code == 400
    assert started.json() == {"location": ["Component pointcloud may only run on the robot."]}
    moved = http.post(f"{COMPONENT}/pointcloud/migrate", json={"location": "cloud"})
    assert moved.status_code == 400


@pytest.mark.parametrize("body", [{}, {"location": "moon"}, {"location": None}])
def test_a_component_start_needs_a_known_location(http, body):
    assert http.post(f"{COMPONENT}/sampler/start", json=body).status_code == 400


def test_migrating_a_component_that_is_not_running_needs_a_target(http):
    response = http.post(f"{COMPONENT}/sampler/migrate", json={})
    assert response.status_code == 400
    assert "location" in response.json()


def test_migrating_a_component_to_where_it_runs_is_refused(http):
    Component.objects.filter(component_id="sampler").update(active_location="robot", status="running")
    assert http.post(f"{COMPONENT}/sampler/migrate", json={"location": "robot"}).status_code == 400


async def test_migrating_without_a_target_moves_the_component_to_the_other_side(daphne_server):
    alice, key = await make_owner("alice")
    token = await make_robot(alice, "alice-bot")
    await sync_to_async(Component.objects.filter(component_id="sampler").update)(active_location="robot")
    async with connected(daphne_server, "alice-bot", token) as robot, async_client(daphne_server, key) as http:
        pending = asyncio.ensure_future(http.post(f"{COMPONENT}/sampler/migrate", json={}))
        command = await robot.next(Event.COMPONENT_MIGRATE)
        response = await pending
    assert command.data == {"skill": SKILL, "component": "sampler", "location": "cloud"}
    assert response.status_code == 200 and response.json()["accepted"] is True


# --------------------------------------------------------------------------- commands to robots


@pytest.mark.parametrize(
    ("path", "body", "event", "data"),
    [
        ("/api/robot/alice-bot/start", None, Event.ROBOT_START, {}),
        ("/api/robot/alice-bot/stop", None, Event.ROBOT_STOP, {}),
        ("/api/robot/alice-bot/shutdown", None, Event.SHUTDOWN, {}),
        (f"/api/robot/alice-bot/skill/{SKILL}/stop", None, Event.SKILL_STOP, {"skill": SKILL}),
        (
            f"{COMPONENT}/detector/start",
            {"location": "cloud"},
            Event.COMPONENT_START,
            {"skill": SKILL, "component": "detector", "location": "cloud"},
        ),
        (
            f"{COMPONENT}/detector/stop",
            {"location": "robot"},
            Event.COMPONENT_STOP,
            {"skill": SKILL, "component": "detector", "location": "robot"},
        ),
        (f"{COMPONENT}/detector/stop", {}, Event.COMPONENT_STOP, {"skill": SKILL, "component": "detector"}),
    ],
)
async def test_a_command_reaches_the_connected_robot_and_its_ack_is_returned(daphne_server, path, body, event, data):
    async with alice_and_her_robot(daphne_server) as (robot, http):
        pending = asyncio.ensure_future(http.post(path, json=body))
        command = await robot.next(event)
        response = await pending
    assert command.data == data
    assert response.status_code == 200, response.text
    answer = response.json()
    assert answer["robot"] == "alice-bot" and answer["event"] == event and answer["accepted"] is True
    assert answer["reply"]["event"] == Event.ACK


async def test_a_skill_start_carries_the_skills_config(daphne_server):
    async with alice_and_her_robot(daphne_server) as (robot, http):
        pending = asyncio.ensure_future(http.post(f"/api/robot/alice-bot/skill/{SKILL}/start"))
        command = await robot.next(Event.SKILL_START)
        assert (await pending).json()["accepted"] is True
    assert command.data["skill"] == SKILL
    assert command.data["config"]["components"].keys() == sample_skill_config()["components"].keys()


async def test_a_robot_that_answers_with_an_error_is_reported_as_not_accepted(daphne_server):
    async with alice_and_her_robot(daphne_server, auto_ack=False) as (robot, http):
        pending = asyncio.ensure_future(http.post(f"/api/robot/alice-bot/skill/{SKILL}/start"))
        command = await robot.next(Event.SKILL_START)
        await robot.send(Event.ERROR_MESSAGE, {"message": "no GPU", "code": "unavailable"}, reply_to=command.id)
        response = await pending
    assert response.status_code == 200
    answer = response.json()
    assert answer["accepted"] is False
    assert answer["reply"]["event"] == Event.ERROR_MESSAGE
    assert answer["reply"]["data"]["message"] == "no GPU"


def test_a_command_to_an_offline_robot_is_a_conflict_at_once(http):
    started = time.monotonic()
    response = http.post("/api/robot/alice-bot/start")
    assert response.status_code == 409
    assert "offline" in response.json()["detail"]
    assert time.monotonic() - started < 1.0


async def test_a_robot_that_never_answers_times_out_after_the_wait(daphne_server):
    async with alice_and_her_robot(daphne_server, auto_ack=False) as (_, http):
        started = time.monotonic()
        response = await http.post("/api/robot/alice-bot/stop?wait=0.5")
        elapsed = time.monotonic() - started
    assert response.status_code == 504
    assert 0.5 <= elapsed < 1.5


@pytest.mark.parametrize("wait", ["soon", "0", "-1", "61", "nan", "inf", ""])
def test_an_invalid_wait_is_refused(http, wait):
    response = http.post(f"/api/robot/alice-bot/start?wait={wait}")
    assert response.status_code == 400, response.text
    assert "wait" in response.json()


async def test_a_fleet_command_reaches_every_connected_robot_of_the_caller_and_reports_each(daphne_server):
    alice, key = await make_owner("alice")
    bob, _ = await make_owner("bob")
    tokens = {robot_id: await make_robot(alice, robot_id, with_skill=False) for robot_id in ("a1", "a2", "a3")}
    bob_token = await make_robot(bob, "bob-bot", with_skill=False)
    async with (
        connected(daphne_server, "a1", tokens["a1"]) as a1,
        connected(daphne_server, "a2", tokens["a2"], auto_ack=False) as a2,
        connected(daphne_server, "bob-bot", bob_token) as bob_robot,
        async_client(daphne_server, key) as http,
    ):
        response = await http.post("/api/robot/start?wait=0.5")
        assert (await a1.next(Event.ROBOT_START)).data == {}
        assert (await a2.next(Event.ROBOT_START)).data == {}
        with pytest.raises(TimeoutError):
            await bob_robot.next(Event.ROBOT_START, timeout=0.3)
    assert response.status_code == 200
    results = {result["robot"]: result for result in response.json()["results"]}
    # a3 is offline, so it is not part of the fleet command; a2 never answered.
    assert set(results) == {"a1", "a2"}
    assert results["a1"]["accepted"] is True and results["a1"]["reply"]["event"] == Event.ACK
    assert results["a2"] == {"robot": "a2", "accepted": False, "error": "no answer within 0.5 s"}


# --------------------------------------------------------------------------- HTTP hygiene


@pytest.mark.parametrize(
    ("method", "path"),
    [
        ("PUT", "/api/robot"),
        ("DELETE", "/api/robot"),
        ("GET", "/api/robot/start"),
        ("PUT", "/api/robot/alice-bot"),
        ("POST", "/api/robot/alice-bot/info"),
        ("GET", "/api/robot/alice-bot/token"),
        ("GET", "/api/robot/alice-bot/start"),
        ("GET", "/api/robot/alice-bot/skill/add"),
        ("GET", f"/api/robot/alice-bot/skill/{SKILL}/start"),
        ("DELETE", f"/api/robot/alice-bot/skill/{SKILL}/info"),
        ("GET", f"{COMPONENT}/sampler/migrate"),
        ("GET", "/api/database/query"),
        ("POST", "/api/events"),
    ],
)
def test_a_wrong_method_is_not_allowed(http, method, path):
    assert http.request(method, path).status_code == 405


def test_a_wrong_method_on_a_staff_route_is_not_allowed_for_staff(daphne_server):
    # Others are refused first (403): DRF checks permissions before the method.
    _, staff = user_with_token("ops", staff=True)
    with client(daphne_server, staff) as http:
        assert http.patch("/api/templates", json={}).status_code == 405
        assert http.put("/api/templates/1", json={}).status_code == 405


def test_a_body_over_a_mebibyte_is_refused_and_nothing_written(daphne_server):
    _, staff = user_with_token("ops", staff=True)
    huge = {"name": "Huge", "description": "x" * (1024 * 1024 + 1), "config": people_counting()}
    just_under = {"name": "Just under", "description": "x" * 1_000_000, "config": people_counting()}
    with client(daphne_server, staff) as http:
        refused = http.post("/api/templates", json=huge)
        accepted = http.post("/api/templates", json=just_under)
    assert refused.status_code == 413, refused.status_code
    assert "limit is 1048576 bytes" in refused.json()["detail"]
    assert accepted.status_code == 201
    assert list(SkillTemplate.objects.values_list("name", flat=True)) == ["Just under"]


def test_a_malformed_json_body_is_a_bad_request(http):
    response = http.post("/api/robot", content=b"{not json", headers={"Content-Type": "application/json"})
    assert response.status_code == 400
