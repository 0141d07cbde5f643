"""Releases over the Robot API, against the real daphne: numbered per Skill, validated, pinned, immutable, per organization."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import httpx
import pytest
from django.contrib.auth import get_user_model
from django.db import DatabaseError, connection, connections
from django.test import Client

from audit.models import AuditEntry
from robots.services import issue_api_token
from rollouts.models import ImmutableError, Release
from rollouts.services import create_release
from teams.models import Organization
from tests.teams.teamutil import headers, login_token, team, user

pytestmark = pytest.mark.django_db(transaction=True)

DIGEST = "sha256:" + "ab" * 32


def config(skill_id: str = "detect", image: str | None = f"bridgeos/detector:1@{DIGEST}") -> dict:
    """Return a Skill of a docker component (``image``) and a process-runtime one without an image."""
    docker = {"image": image, "command": ["sleep", "600"]} if image else {"command": ["sleep", "600"]}
    process = {"command": ["python3", "-m", "sampler"]}
    return {
        "skill": skill_id.title(),
        "skill_id": skill_id,
        "components": {
            "detector": {"name": "Detector", "location": "either", "robot": docker, "cloud": dict(docker)},
            "sampler": {"name": "Sampler", "location": "robot", "robot": process},
        },
    }


@pytest.fixture
def lab() -> Organization:
    """A team with a developer, an operator and a viewer; another team with its own developer."""
    team("other", eve="developer")
    return team("lab", dev="developer", op="operator", viewer="viewer")


@pytest.fixture
def http(daphne_server) -> Iterator[dict[str, httpx.Client]]:
    """Return a Robot API client per member of the lab, each with a login token."""
    clients = {}
    for name in ("dev", "op", "viewer", "eve"):
        who = get_user_model().objects.get(username=name)
        clients[name] = httpx.Client(base_url=daphne_server.url + "/api", headers=headers(login_token(who)), timeout=30)
    yield clients
    for client in clients.values():
        client.close()


def make(client: httpx.Client, **body) -> httpx.Response:
    """Ask for a release of the lab unless the body names another organization."""
    return client.post("/releases", json={"organization": "lab", "config": config(), **body})


def test_a_developer_makes_releases_numbered_per_skill(lab, http):
    first = make(http["dev"], name="First", notes="Detects people.")
    assert first.status_code == 201, first.text
    made = first.json()
    assert made["organization"] == "lab" and made["skill_id"] == "detect" and made["number"] == 1
    assert (made["name"], made["notes"], made["created_by"]) == ("First", "Detects people.", "dev")
    assert made["config"]["components"]["detector"]["robot"]["image"] == f"bridgeos/detector:1@{DIGEST}"
    assert made["config"]["components"]["sampler"]["robot"]["image"] is None, "a process component needs no image"

    assert make(http["dev"]).json()["number"] == 2
    assert make(http["dev"], config=config("map")).json()["number"] == 1
    assert make(http["eve"], organization="other").json()["number"] == 1, "numbers are per organization"
    assert sorted(Release.objects.values_list("organization__slug", "skill_id", "number")) == [
        ("lab", "detect", 1),
        ("lab", "detect", 2),
        ("lab", "map", 1),
        ("other", "detect", 1),
    ]


def test_an_operator_is_refused_and_another_organization_is_as_unknown_as_a_missing_one(lab, http):
    refused = make(http["op"])
    assert refused.status_code == 403, refused.text
    assert "developer" in refused.json()["detail"]
    other, missing = make(http["dev"], organization="other"), make(http["dev"], organization="no-such-org")
    assert other.status_code == missing.status_code == 404
    assert other.json() == missing.json() == {"organization": ["No such organization of yours."]}
    assert not Release.objects.exists()


def test_a_member_of_several_organizations_names_one_unless_their_token_is_scoped(lab, http, daphne_server):
    unnamed = http["dev"].post("/releases", json={"config": config()})
    assert unnamed.status_code == 400 and "organization" in unnamed.json(), unnamed.text
    dev = get_user_model().objects.get(username="dev")
    scoped = issue_api_token(dev, organization=lab, role="developer", name="ci")[0]
    with httpx.Client(base_url=daphne_server.url + "/api", headers=headers(scoped), timeout=30) as client:
        answer = client.post("/releases", json={"config": config()})
        assert answer.status_code == 201, answer.text
        assert answer.json()["organization"] == "lab"
        # The token's scope holds: naming the user's personal organization finds nothing.
        assert client.post("/releases", json={"organization": "dev", "config": config()}).status_code == 404
    alone = user("solo")
    with httpx.Client(base_url=daphne_server.url + "/api", headers=headers(login_token(alone)), timeout=30) as client:
        answer = client.post("/releases", json={"config": config()})
        assert answer.status_code == 201 and answer.json()["organization"] == "solo", answer.text


def test_an_invalid_config_is_refused_naming_the_field_and_nothing_is_made(lab, http):
    bad = config()
    bad["components"]["detector"]["location"] = "moon"
    answer = make(http["dev"], config=bad)
    assert answer.status_code == 400, answer.text
    assert "components.detector.location" in answer.text
    not_an_object = make(http["dev"], config=["detect"])
    assert not_an_object.status_code == 400 and "config" in not_an_object.json(), not_an_object.text
    too_long = make(http["dev"], name="x" * 201)
    assert too_long.status_code == 400 and "name" in too_long.json(), too_long.text
    assert not Release.objects.exists()


@pytest.mark.parametrize("image", ["docker.io/library/redis:7", "bridgeos/detector:1", "redis@sha256:abc"])
def test_an_image_not_pinned_by_digest_is_refused_naming_the_field(lab, http, image):
    answer = make(http["dev"], config=config(image=image))
    assert answer.status_code == 400, answer.text
    problems = answer.json()["config"]
    assert {problem.split(":")[0] for problem in problems} == {
        "components.detector.robot.image",
        "components.detector.cloud.image",
    }
    assert "not pinned by digest" in problems[0]
    assert not Release.objects.exists()


def test_concurrent_creates_get_distinct_numbers(lab):
    dev = get_user_model().objects.get(username="dev")
    count = 8
    start, numbers, errors = threading.Barrier(count), [], []

    def release() -> None:
        try:
            start.wait()
            numbers.append(create_release(lab, config(), user=dev).number)
        except Exception as exc:  # reported below: a thread's failure must fail the test
            errors.append(exc)
        finally:
            connections.close_all()

    threads = [threading.Thread(target=release) for _ in range(count)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    assert sorted(numbers) == list(range(1, count + 1))


def test_the_database_refuses_to_update_a_release_and_the_model_refuses_to_save_one(lab):
    dev = get_user_model().objects.get(username="dev")
    release = create_release(lab, config(), name="Kept", user=dev)
    with pytest.raises(DatabaseError, match="immutable"), connection.cursor() as cursor:
        cursor.execute("UPDATE rollouts_release SET name = 'Changed' WHERE id = %s", [release.pk])
    with pytest.raises(DatabaseError, match="immutable"):
        Release.objects.filter(pk=release.pk).update(config={})
    release.name = "Changed"
    with pytest.raises(ImmutableError):
        release.save()
    assert Release.objects.get(pk=release.pk).name == "Kept"
    # The author's account may go: the release keeps who made it.
    dev.delete()
    kept = Release.objects.get(pk=release.pk)
    assert (kept.created_by_id, kept.created_by_name, kept.name) == (None, "dev", "Kept")
    # And it leaves with its organization alone.
    lab.delete()
    assert not Release.objects.filter(pk=release.pk).exists()


def test_releases_are_listed_and_read_only_in_the_callers_organizations(lab, http):
    ours = make(http["dev"]).json()
    make(http["dev"], config=config("map"))
    theirs = make(http["eve"], organization="other").json()

    listed = http["viewer"].get("/releases")
    assert listed.status_code == 200, listed.text
    assert listed.json()["count"] == 2
    assert {row["skill_id"] for row in listed.json()["results"]} == {"detect", "map"}
    only = http["viewer"].get("/releases", params={"skill": "detect"}).json()["results"]
    assert [row["id"] for row in only] == [ours["id"]]
    assert http["viewer"].get("/releases", params={"organization": "other"}).json()["count"] == 0
    assert http["viewer"].get("/releases", params={"skill": "Not A Slug"}).status_code == 400

    assert http["viewer"].get(f"/releases/{ours['id']}").json() == ours
    other, missing = http["viewer"].get(f"/releases/{theirs['id']}"), http["viewer"].get("/releases/999999")
    assert other.status_code == missing.status_code == 404
    assert other.json() == missing.json()
    assert http["viewer"].get("/releases/99999999999999999999").status_code == 404, "past bigint: still a 404"
    assert http["eve"].get(f"/releases/{theirs['id']}").status_code == 200


def test_a_release_is_never_edited_over_the_api(lab, http):
    made = make(http["dev"]).json()
    for method in ("PUT", "PATCH", "DELETE"):
        assert http["dev"].request(method, f"/releases/{made['id']}", json={"name": "x"}).status_code == 405
    assert http["dev"].get(f"/releases/{made['id']}").json() == made


def test_making_a_release_is_audited_in_its_organization(lab, http):
    made = make(http["dev"]).json()
    make(http["op"])
    entries = AuditEntry.objects.filter(action="release.create").order_by("id")
    assert [(e.actor, e.object, e.organization_slug, e.status, e.outcome) for e in entries] == [
        ("dev", f"release/{made['id']}", "lab", 201, "ok"),
        ("op", "", "lab", 403, "denied"),
    ]


def test_the_admin_shows_releases_read_only(lab):
    staff = get_user_model().objects.create_user("root", is_staff=True, is_superuser=True)
    release = create_release(lab, config(), name="Shown")
    browser = Client()
    browser.force_login(staff)
    assert browser.get("/admin/rollouts/release/").status_code == 200
    detail = browser.get(f"/admin/rollouts/release/{release.pk}/change/")
    assert detail.status_code == 200 and "Shown" in detail.content.decode()
    assert browser.get("/admin/rollouts/release/add/").status_code == 403
    changed = browser.post(f"/admin/rollouts/release/{release.pk}/change/", {"name": "Changed"})
    assert changed.status_code == 403
    assert browser.post(f"/admin/rollouts/release/{release.pk}/delete/", {"post": "yes"}).status_code == 403
    assert Release.objects.get(pk=release.pk).name == "Shown"
