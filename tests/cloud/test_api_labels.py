"""Robot labels through the Robot API and the robot door, against daphne, PostgreSQL and a real agent process."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import httpx
import pytest
from asgiref.sync import sync_to_async
from django.contrib.auth import get_user_model

from bridgeos_agent.link import AuthenticationError
from monitoring.models import Event as LogEvent
from robots.models import Robot
from tests.conftest import BIN, stop_process
from tests.logguard import watch
from tests.teams.teamutil import headers, login_token, robot_in, team

from .wsutil import robot_login

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(120)]


def api(server, token: str) -> httpx.Client:
    """Return an HTTP client of the Robot API sending a token."""
    return httpx.Client(base_url=server.url + "/api", headers=headers(token), timeout=15)


@pytest.fixture
def lab(daphne_server):
    """A team `lab` (ada admin, otto operator) with two robots, and a team `other` (bob admin) with one."""
    lab = team("lab", ada="admin", otto="operator")
    robot_in(lab, "lab-1")
    robot_in(lab, "lab-2")
    other = team("other", bob="admin")
    robot_in(other, "other-1")
    Robot.objects.filter(id="lab-1").update(labels={"site": "lab", "model": "turtlebot"})
    Robot.objects.filter(id="lab-2").update(labels={"site": "field", "model": "turtlebot"})
    Robot.objects.filter(id="other-1").update(labels={"site": "lab", "model": "turtlebot"})
    return lab


def labels_of(robot_id: str) -> dict[str, str]:
    return Robot.objects.values_list("labels", flat=True).get(id=robot_id)


def test_an_admin_replaces_a_robots_labels_and_every_robot_view_shows_them(daphne_server, lab):
    with api(daphne_server, login_token(user_named("ada"))) as http:
        answer = http.patch("/robot/lab-1", json={"labels": {"site": "lab", "arm": "UR5e", "gpu": ""}})
        assert answer.status_code == 200, answer.text
        assert answer.json()["labels"] == {"site": "lab", "arm": "UR5e", "gpu": ""}
        assert http.get("/robot/lab-1").json()["labels"] == {"site": "lab", "arm": "UR5e", "gpu": ""}
        assert http.get("/robot/lab-1/info").json()["labels"]["arm"] == "UR5e"
        listed = {robot["id"]: robot["labels"] for robot in http.get("/robot").json()}
        assert listed == {"lab-1": {"site": "lab", "arm": "UR5e", "gpu": ""}, "lab-2": labels_of("lab-2")}
        assert http.get("/robot", params={"fields": "id,labels", "limit": 1}).json()["results"] == [
            {"id": "lab-1", "labels": {"site": "lab", "arm": "UR5e", "gpu": ""}}
        ]
        assert http.patch("/robot/lab-1", json={"labels": {}}).json()["labels"] == {}
    assert labels_of("lab-1") == {}
    assert LogEvent.objects.filter(robot_id="lab-1", kind="robot_updated", data__labels={}).exists()


def user_named(username: str):
    return get_user_model().objects.get(username=username)


def test_an_operator_may_not_change_labels_and_another_organization_does_not_see_the_robot(daphne_server, lab):
    with api(daphne_server, login_token(user_named("otto"))) as http:
        refused = http.patch("/robot/lab-1", json={"labels": {"site": "moon"}})
        assert refused.status_code == 403, refused.text
        assert http.get("/robot/lab-1").json()["labels"] == {"site": "lab", "model": "turtlebot"}
    with api(daphne_server, login_token(user_named("bob"))) as http:
        assert http.patch("/robot/lab-1", json={"labels": {"site": "moon"}}).status_code == 404
    assert labels_of("lab-1") == {"site": "lab", "model": "turtlebot"}


@pytest.mark.parametrize(
    ("labels", "named"),
    [
        ({"Site": "lab"}, "'Site'"),
        ({"site": "lab", "model": "bad value"}, "'model'"),
        ({"site": 3}, "'site'"),
        ({f"k{i}": "v" for i in range(65)}, "at most 64 labels"),
        (["site=lab"], "object"),
        ("site=lab", "object"),
    ],
)
def test_bad_labels_are_a_400_naming_the_key_and_change_nothing(daphne_server, lab, labels, named):
    with api(daphne_server, login_token(user_named("ada"))) as http:
        answer = http.patch("/robot/lab-1", json={"name": "Renamed", "labels": labels})
    assert answer.status_code == 400, answer.text
    assert list(answer.json()) == ["labels"]
    assert named in " ".join(answer.json()["labels"]), answer.json()
    robot = Robot.objects.get(id="lab-1")
    assert (robot.name, robot.labels) == ("", {"site": "lab", "model": "turtlebot"})


def test_a_robot_created_through_the_api_takes_its_labels_and_bad_ones_create_nothing(daphne_server, lab):
    with api(daphne_server, login_token(user_named("ada"))) as http:
        made = http.post("/robot", json={"id": "lab-3", "organization": "lab", "labels": {"site": "lab"}})
        assert made.status_code == 201, made.text
        assert made.json()["labels"] == {"site": "lab"}
        bad = http.post("/robot", json={"id": "lab-4", "organization": "lab", "labels": {"site": "-"}})
        assert bad.status_code == 400 and "'site'" in bad.json()["labels"][0], bad.text
    assert labels_of("lab-3") == {"site": "lab"}
    assert not Robot.objects.filter(id="lab-4").exists()


@pytest.mark.parametrize(
    ("selector", "ids"),
    [
        ("site=lab", ["lab-1"]),
        ("model=turtlebot", ["lab-1", "lab-2"]),
        ("model=turtlebot,site!=lab", ["lab-2"]),
        ("site,!gpu", ["lab-1", "lab-2"]),
        ("gpu", []),
    ],
)
def test_a_selector_filters_the_fleet_and_never_reaches_another_organizations_robot(daphne_server, lab, selector, ids):
    with api(daphne_server, login_token(user_named("otto"))) as http:
        listed = http.get("/robot", params={"selector": selector})
        assert listed.status_code == 200, listed.text
        assert [robot["id"] for robot in listed.json()] == ids
        page = http.get("/robot", params={"selector": selector, "limit": 10, "fields": "id"}).json()
        assert page["count"] == len(ids)
        assert [robot["id"] for robot in page["results"]] == ids
    # bob's other-1 matches site=lab too, but only his own robot is in his answer.
    with api(daphne_server, login_token(user_named("bob"))) as http:
        assert [robot["id"] for robot in http.get("/robot", params={"selector": "site=lab"}).json()] == ["other-1"]


@pytest.mark.parametrize(
    ("selector", "said"), [("Site=lab", "'Site=lab'"), ("site=lab,,", "''"), ("site==x", "'site==x'"), ("", "term")]
)
def test_a_bad_selector_is_a_400_naming_selector_and_the_term(daphne_server, lab, selector, said):
    with api(daphne_server, login_token(user_named("otto"))) as http:
        answer = http.get("/robot", params={"selector": selector})
    assert answer.status_code == 400, answer.text
    assert list(answer.json()) == ["selector"]
    assert said in answer.json()["selector"][0]


# --------------------------------------------------------------------------- the robot door


async def test_labels_sent_at_login_apply_only_while_the_robot_has_none(daphne_server):
    lab = await sync_to_async(team)("lab", ada="admin")
    token = await sync_to_async(robot_in)(lab, "door-1")
    link, _ = await robot_login(daphne_server, "door-1", token, labels={"site": "lab"})
    await link.close()
    assert await sync_to_async(labels_of)("door-1") == {"site": "lab"}
    link, _ = await robot_login(daphne_server, "door-1", token, labels={"site": "field", "arm": "x"})
    await link.close()
    assert await sync_to_async(labels_of)("door-1") == {"site": "lab"}
    # A login without labels (an outside client that never heard of them) keeps them as they are.
    link, _ = await robot_login(daphne_server, "door-1", token)
    await link.close()
    assert await sync_to_async(labels_of)("door-1") == {"site": "lab"}


async def test_invalid_labels_at_login_are_refused_naming_the_key_and_change_nothing(daphne_server):
    lab = await sync_to_async(team)("lab", ada="admin")
    token = await sync_to_async(robot_in)(lab, "door-2")
    with pytest.raises(AuthenticationError, match=r"invalid labels: label key 'Site' is invalid"):
        await robot_login(daphne_server, "door-2", token, labels={"Site": "lab"})
    robot = await sync_to_async(Robot.objects.get)(id="door-2")
    assert (robot.labels, robot.connected) == ({}, False)


# --------------------------------------------------------------------------- a real agent


def start_agent(master: str, robot_id: str, token: str, data_dir: Path, log: Path, *labels: str) -> subprocess.Popen:
    """Start the real agent, simulated, with --label flags."""
    command = [str(BIN / "bridgeos-agent"), "run", "--master", master, "--robot", robot_id, "--token", token]
    command += ["--runtime", "process", "--simulate", "--data-dir", str(data_dir)]
    for label in labels:
        command += ["--label", label]
    env = {key: value for key, value in os.environ.items() if not key.startswith("BRIDGEOS_")}
    with watch(log).open("ab") as out:
        return subprocess.Popen(command, env={**env, "PYTHONUNBUFFERED": "1"}, stdout=out, stderr=subprocess.STDOUT)


def wait_for(check, what: str, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.2)


def test_a_real_agent_registers_its_labels_at_first_login_and_a_later_run_does_not_override(daphne_server, tmp_path):
    lab = team("lab", ada="admin")
    token = robot_in(lab, "agent-1")
    log = tmp_path / "agent.log"

    def connected_once_more(count: int):
        return lambda: log.read_text(errors="replace").count("connected to the cloud (") >= count

    agent = start_agent(daphne_server.ws_url, "agent-1", token, tmp_path / "data", log, "site=lab", "model=turtlebot")
    try:
        wait_for(connected_once_more(1), "the agent's first login")
        assert labels_of("agent-1") == {"site": "lab", "model": "turtlebot"}
    finally:
        stop_process(agent)
    assert LogEvent.objects.filter(robot_id="agent-1", kind="robot_labels_registered").count() == 1

    agent = start_agent(daphne_server.ws_url, "agent-1", token, tmp_path / "data", log, "site=field,arm=ur5")
    try:
        wait_for(connected_once_more(2), "the agent's second login")
        assert labels_of("agent-1") == {"site": "lab", "model": "turtlebot"}
    finally:
        stop_process(agent)
    assert LogEvent.objects.filter(robot_id="agent-1", kind="robot_labels_registered").count() == 1


def test_the_agent_refuses_a_bad_label_before_it_connects(tmp_path):
    command = [str(BIN / "bridgeos-agent"), "run", "--master", "ws://127.0.0.1:9", "--robot", "r", "--token", "t"]
    env = {key: value for key, value in os.environ.items() if not key.startswith("BRIDGEOS_")}
    flag = subprocess.run([*command, "--label", "Site=lab"], env=env, capture_output=True, text=True, timeout=60)
    assert flag.returncode == 2
    assert "--label (env BRIDGEOS_LABELS): label key 'Site' is invalid" in flag.stderr
    from_env = subprocess.run(
        command, env={**env, "BRIDGEOS_LABELS": "site"}, capture_output=True, text=True, timeout=60
    )
    assert from_env.returncode == 2
    assert "label 'site' has no '='" in from_env.stderr
