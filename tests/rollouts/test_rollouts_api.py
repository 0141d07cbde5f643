"""Rollouts over the Robot API, against the real daphne: made per organization, validated field by field, steered.

No agent runs here (tests/rollouts/test_rollout_agents.py drives real ones): the robots are
offline, so the executor stores the release as each one's desired version.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator

import httpx
import pytest
from django.contrib.auth import get_user_model

from audit.models import AuditEntry
from robots.models import Robot
from robots.services import create_robot
from rollouts import executor
from rollouts.models import Rollout, RolloutRobot, UpdateHold
from rollouts.services import create_release
from skills.models import Skill
from teams.models import Organization
from tests.rollouts.test_releases import config
from tests.teams.teamutil import headers, login_token, team

pytestmark = pytest.mark.django_db(transaction=True)


@pytest.fixture
def lab() -> Organization:
    """The lab (a developer, an operator, a viewer) with six robots, and another team with two of its own."""
    other = team("other", eve="developer")
    lab = team("lab", dev="developer", op="operator", viewer="viewer", boss="admin")
    dev, eve = (get_user_model().objects.get(username=name) for name in ("dev", "eve"))
    for n in range(6):
        create_robot(f"lab-{n}", dev, organization=lab, labels={"site": "lab", "model": "tb3" if n < 4 else "tb4"})
    for n in range(2):
        create_robot(f"other-{n}", eve, organization=other, labels={"site": "lab", "model": "tb3"})
    return lab


@pytest.fixture
def http(daphne_server) -> Iterator[dict[str, httpx.Client]]:
    clients = {}
    for name in ("dev", "op", "viewer", "boss", "eve"):
        who = get_user_model().objects.get(username=name)
        clients[name] = httpx.Client(base_url=daphne_server.url + "/api", headers=headers(login_token(who)), timeout=30)
    yield clients
    for client in clients.values():
        client.close()


def settle(check: Callable[[], bool], timeout: float = 15, what: Callable[[], object] | None = None) -> None:
    """Take executor steps until ``check`` holds (a Celery worker of the suite may take some of them)."""
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            pytest.fail(f"not settled after {timeout} s: {what() if what else ''}")
        executor.tick()
        time.sleep(0.05)


@pytest.fixture
def release(lab):
    return create_release(lab, config(), user=get_user_model().objects.get(username="dev"))


def test_a_developer_rolls_a_release_out_to_a_group_of_their_organization_in_planned_batches(
    lab, http, release, daphne_server
):
    made = http["dev"].post(
        "/rollouts",
        json={"release": release.pk, "selector": "site=lab,model=tb3", "strategy": {"first": "25%", "factor": 2}},
    )
    assert made.status_code == 201, made.text
    body = made.json()
    assert (body["organization"], body["skill_id"], body["release_number"]) == ("lab", "detect", 1)
    assert body["state"] == "running" and body["batch_sizes"] == [1, 2, 1]
    assert [robot["robot"] for robot in body["robots"]] == ["lab-0", "lab-1", "lab-2", "lab-3"]
    assert [batch["size"] for batch in body["batches"]] == [1, 2, 1]
    assert body["counts"]["pending"] == 4
    # eve's robots match the selector's labels too, but a selector never leaves the release's organization.
    assert not RolloutRobot.objects.filter(robot__organization__slug="other").exists()
    entry = AuditEntry.objects.get(actor="dev", status=201)
    assert (entry.organization_slug, entry.action, entry.object) == ("lab", "rollout.create", f"rollout/{body['id']}")

    listed = http["viewer"].get("/rollouts").json()
    assert [r["id"] for r in listed["results"]] == [body["id"]]
    assert http["eve"].get("/rollouts").json()["results"] == []
    assert http["eve"].get(f"/rollouts/{body['id']}").status_code == 404

    # Offline robots get the release as their desired version: it is stored, and they converge at login.
    settle(lambda: RolloutRobot.objects.get(rollout_id=body["id"], robot_id="lab-0").status == "offline")
    assert RolloutRobot.objects.get(rollout_id=body["id"], robot_id="lab-0").touched
    assert Skill.objects.get(robot_id="lab-0", skill_id="detect").config == release.config
    assert not Skill.objects.filter(robot_id="lab-1").exists(), "the next batch waits for the canary"

    scrape = httpx.get(f"{daphne_server.url}/metrics", timeout=30).text
    assert 'bridgeos_rollouts{state="running"} 1.0' in scrape
    assert 'bridgeos_rollout_robots{status="offline"} 1.0' in scrape
    assert 'bridgeos_rollout_robots{status="pending"} 3.0' in scrape


@pytest.mark.parametrize(
    ("body", "field"),
    [
        ({"selector": "site=lab,,"}, "selector"),
        ({"selector": "site=nowhere"}, "selector"),
        ({"release": 999999}, "release"),
        ({"release": "one"}, "release"),
        ({"strategy": {"first": "0%"}}, "strategy.first"),
        ({"strategy": {"growth": "linear"}}, "strategy.growth"),
        ({"strategy": {"soak": 5}}, "strategy.soak"),
        ({"gates": {"conditions": ["cpu <"]}}, "gates.conditions[0]"),
        ({"gates": {"conditions": ["temperature < 3"]}}, "gates.conditions[0]"),
        ({"gates": {"rules": []}}, "gates.rules"),
        ({"gates": {"router_dropped_max": 5}}, "gates.router_dropped_max"),
        ({"gates": {"router_dropped_max": "5%"}}, "gates.router_dropped_max"),
        ({"follow": "maybe"}, "follow"),
    ],
)
def test_a_bad_rollout_is_refused_naming_its_field_and_nothing_is_made(lab, http, release, body, field):
    answer = http["dev"].post("/rollouts", json={"release": release.pk, "selector": "site=lab", **body})
    assert answer.status_code == 400, answer.text
    assert field in answer.json(), answer.json()
    assert not Rollout.objects.exists() and not RolloutRobot.objects.exists()


def test_another_organizations_release_and_a_selector_matching_only_their_robots_reach_nothing(lab, http, release):
    other = Organization.objects.get(slug="other")
    theirs = create_release(other, config(), user=get_user_model().objects.get(username="eve"))
    # dev names eve's release: as unknown as a missing one.
    answer = http["dev"].post("/rollouts", json={"release": theirs.pk, "selector": "site=lab"})
    assert answer.status_code == 400 and "release" in answer.json()
    # eve's selector names only the lab's robots' label: it matches nothing of hers.
    answer = http["eve"].post("/rollouts", json={"release": theirs.pk, "selector": "model=tb4"})
    assert answer.status_code == 400 and "selector" in answer.json()
    assert not Rollout.objects.exists()


def test_only_a_developer_rolls_out_and_steers(lab, http, release):
    for name in ("op", "viewer"):
        answer = http[name].post("/rollouts", json={"release": release.pk, "selector": "site=lab"})
        assert answer.status_code == 403, (name, answer.text)
    rollout = http["dev"].post("/rollouts", json={"release": release.pk, "selector": "site=lab"}).json()
    assert http["op"].post(f"/rollouts/{rollout['id']}/pause").status_code == 403
    assert http["eve"].post(f"/rollouts/{rollout['id']}/pause").status_code == 404
    assert Rollout.objects.get().state == "running"


def test_pause_resume_and_abort_move_a_rollout_and_refuse_what_its_state_does_not_allow(lab, http, release):
    rollout = http["dev"].post("/rollouts", json={"release": release.pk, "selector": "site=lab"}).json()
    url = f"/rollouts/{rollout['id']}"
    assert http["dev"].post(url + "/resume").status_code == 409
    paused = http["dev"].post(url + "/pause")
    assert paused.status_code == 200 and paused.json()["state"] == "paused"
    assert paused.json()["reason"] == "paused by dev"
    assert http["dev"].post(url + "/pause").status_code == 409
    before = sorted(RolloutRobot.objects.values_list("robot_id", "status", "updated_at"))
    executor.tick()
    assert sorted(RolloutRobot.objects.values_list("robot_id", "status", "updated_at")) == before, "paused: no step"
    assert http["dev"].post(url + "/resume").json()["state"] == "running"
    settle(lambda: RolloutRobot.objects.get(robot_id="lab-0").status == "offline")

    # An abort puts back what the rollout touched: lab-0 had no such Skill, so it has none again.
    assert http["dev"].post(url + "/abort").json()["state"] == "rolling_back"
    settle(lambda: Rollout.objects.get().state == "aborted")
    done = http["dev"].get(url).json()
    assert done["state"] == "aborted", done
    assert done["counts"]["rolled_back"] == 1 and done["counts"]["pending"] == 5
    assert not Skill.objects.filter(robot_id="lab-0", skill_id="detect").exists()
    assert http["dev"].post(url + "/abort").status_code == 409


def test_a_second_rollout_of_the_same_skill_over_the_same_robots_waits_for_the_first(lab, http, release):
    first = http["dev"].post("/rollouts", json={"release": release.pk, "selector": "model=tb3"})
    assert first.status_code == 201
    clash = http["dev"].post("/rollouts", json={"release": release.pk, "selector": "site=lab"})
    assert clash.status_code == 409 and "lab-0" in clash.json()["detail"]
    assert http["dev"].post("/rollouts", json={"release": release.pk, "selector": "model=tb4"}).status_code == 201


def test_a_followed_group_takes_robots_labelled_or_created_later(lab, http, release):
    rollout = (
        http["dev"].post("/rollouts", json={"release": release.pk, "selector": "site=annex", "follow": True}).json()
    )
    assert rollout["robots"] == []
    assert http["boss"].patch("/robot/lab-5", json={"labels": {"site": "annex"}}).status_code == 200
    create_robot("annex-new", get_user_model().objects.get(username="dev"), organization=lab, labels={"site": "annex"})

    def members() -> dict[str, str]:
        return dict(RolloutRobot.objects.filter(rollout_id=rollout["id"]).values_list("robot_id", "status"))

    settle(lambda: members() == {"lab-5": "offline", "annex-new": "offline"}, what=members)


def test_an_owner_holds_and_releases_a_robots_updates(lab, http):
    held = http["op"].post("/robot/lab-0/hold", json={"seconds": 600, "reason": "mapping the warehouse"})
    assert held.status_code == 200, held.text
    assert held.json()["hold"]["holder"] == "owner op" and held.json()["hold"]["reason"] == "mapping the warehouse"
    assert http["viewer"].get("/robot/lab-0/hold").json()["hold"]["holder"] == "owner op"
    assert http["viewer"].post("/robot/lab-0/hold", json={"seconds": 60}).status_code == 403
    assert http["eve"].get("/robot/lab-0/hold").status_code == 404
    for seconds in (0, -5, 10**9):
        answer = http["op"].post("/robot/lab-0/hold", json={"seconds": seconds})
        assert answer.status_code == 400 and "seconds" in answer.json()
    assert UpdateHold.objects.get().reason == "mapping the warehouse", "a refused hold changes nothing"
    assert http["op"].delete("/robot/lab-0/hold").status_code == 204
    assert http["op"].get("/robot/lab-0/hold").json()["hold"] is None
    assert not Robot.objects.get(id="lab-0").rollouts.exists()
