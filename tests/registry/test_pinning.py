"""A Skill's images in the cloud's registry are pinned by digest when it is added; what cannot be pinned is refused."""

from __future__ import annotations

import json

import pytest
from django.contrib.auth import get_user_model
from rest_framework.test import APIClient

from robots.models import Robot
from skills.models import Skill
from skills.services import add_skill

from .conftest import make_fleet
from .test_docker_registry import PUSH_PROBE, push, run

pytestmark = [pytest.mark.docker, pytest.mark.django_db(transaction=True), pytest.mark.log_errors(PUSH_PROBE)]


@pytest.fixture
def own_registry(settings, registry):
    """Make the test registry the cloud's own, as BRIDGEOS_REGISTRY_HOST does."""
    settings.BRIDGEOS = {**settings.BRIDGEOS, "REGISTRY_HOST": registry.host}
    return registry


def config(image: str, skill_id: str = "pin") -> dict:
    """Return a Skill of one movable component running ``image`` on the robot and in the cloud."""
    launch = {"image": image, "command": ["sleep", "600"]}
    component = {"name": "Hello", "location": "either", "robot": launch, "cloud": dict(launch)}
    local = {"name": "Base", "location": "robot", "robot": {"image": "bridgeos/base:bookworm", "command": ["true"]}}
    return {"skill": "Pin", "skill_id": skill_id, "components": {"hello": component, "base": local}}


def digest_of(registry, reference: str, account) -> str:
    """Ask the registry (with skopeo) for the digest a tag points at now."""
    done = run(
        "skopeo", "inspect", "--tls-verify=false", "--creds", account.creds, f"docker://{registry.host}/{reference}"
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)["Digest"]


def test_adding_a_skill_pins_its_images_and_a_moved_tag_changes_nothing(own_registry, tiny_image):
    fleet = make_fleet()
    assert push(own_registry, tiny_image, "alice/pin:1", fleet.alice_token).returncode == 0
    digest = digest_of(own_registry, "alice/pin:1", fleet.alice_token)
    robot = Robot.objects.get(id=fleet.alice_robot.name)

    skill = add_skill(robot, config(f"{own_registry.host}/alice/pin:1"))

    pinned = f"{own_registry.host}/alice/pin:1@{digest}"
    stored = Skill.objects.get(pk=skill.pk).config["components"]
    assert stored["hello"]["robot"]["image"] == stored["hello"]["cloud"]["image"] == pinned
    assert stored["base"]["robot"]["image"] == "bridgeos/base:bookworm", "a local image is kept as written"
    # The tag moves to other bytes: the Skill still runs what it was added with.
    other = f"bridgeos-test/pin-other:{digest[7:15]}"
    assert run("docker", "tag", "bridgeos/base:bookworm", other).returncode == 0
    try:
        assert push(own_registry, other, "alice/pin:1", fleet.alice_token).returncode == 0
    finally:
        run("docker", "rmi", other)
    assert digest_of(own_registry, "alice/pin:1", fleet.alice_token) != digest
    assert Skill.objects.get(pk=skill.pk).config["components"]["hello"]["robot"]["image"] == pinned
    # And the API shows the digest the robot runs.
    api = APIClient()
    api.force_authenticate(get_user_model().objects.get(username="alice"))
    answer = api.get(f"/api/robot/{robot.id}/skill/pin/info")
    assert answer.status_code == 200, answer.content
    assert pinned in answer.content.decode()


@pytest.mark.log_errors(r'err.code="manifest unknown"')
def test_a_missing_tag_or_an_image_the_owner_may_not_pull_is_refused_and_nothing_is_added(own_registry, tiny_image):
    fleet = make_fleet()
    assert push(own_registry, tiny_image, "alice/pin:2", fleet.alice_token).returncode == 0
    api = APIClient()
    api.force_authenticate(get_user_model().objects.get(username="bob"))
    bob_robot = fleet.bob_robot.name

    answer = api.post(
        f"/api/robot/{bob_robot}/skill/add", {"config": config(f"{own_registry.host}/alice/pin:2")}, format="json"
    )
    assert answer.status_code == 400, answer.content
    said = json.dumps(answer.json())
    assert "components.hello.robot.image" in said and "may not pull" in said and "alice/pin:2" in said

    api.force_authenticate(get_user_model().objects.get(username="alice"))
    answer = api.post(
        f"/api/robot/{fleet.alice_robot.name}/skill/add",
        {"config": config(f"{own_registry.host}/alice/never-pushed:1")},
        format="json",
    )
    assert answer.status_code == 400, answer.content
    assert "has no alice/never-pushed:1" in json.dumps(answer.json())
    assert not Skill.objects.exists()
