"""A release's images in the cloud's registry are pinned by digest as its organization's robots pull them."""

from __future__ import annotations

import json

import pytest
from django.contrib.auth import get_user_model
from rest_framework.test import APIClient

from rollouts.models import Release
from rollouts.services import create_release
from teams.services import personal_organization
from tests.registry.conftest import make_fleet
from tests.registry.test_docker_registry import PUSH_PROBE, push
from tests.registry.test_pinning import config, digest_of

pytestmark = [pytest.mark.docker, pytest.mark.django_db(transaction=True), pytest.mark.log_errors(PUSH_PROBE)]


@pytest.fixture
def own_registry(settings, registry):
    """Make the test registry the cloud's own, as BRIDGEOS_REGISTRY_HOST does."""
    settings.BRIDGEOS = {**settings.BRIDGEOS, "REGISTRY_HOST": registry.host}
    return registry


def pinned_only(image: str) -> dict:
    """Return the pinning tests' Skill without its local, unpinned component."""
    skill = config(image, "pin")
    del skill["components"]["base"]
    return skill


@pytest.mark.log_errors(r'err.code="manifest unknown"')
def test_a_tag_of_the_clouds_registry_is_pinned_by_digest_and_what_cannot_be_is_refused(own_registry, tiny_image):
    fleet = make_fleet()
    assert push(own_registry, tiny_image, "alice/pin:1", fleet.alice_token).returncode == 0
    digest = digest_of(own_registry, "alice/pin:1", fleet.alice_token)
    users = get_user_model().objects
    alice, bob = users.get(username="alice"), users.get(username="bob")

    release = create_release(personal_organization(alice), pinned_only(f"{own_registry.host}/alice/pin:1"), user=alice)

    stored = Release.objects.get(pk=release.pk).config["components"]["hello"]
    assert stored["robot"]["image"] == stored["cloud"]["image"] == f"{own_registry.host}/alice/pin:1@{digest}"

    api = APIClient()
    api.force_authenticate(bob)
    # Bob's organization may not pull Alice's image: refused, naming the field, nothing made.
    answer = api.post("/api/releases", {"config": pinned_only(f"{own_registry.host}/alice/pin:1")}, format="json")
    assert answer.status_code == 400, answer.content
    said = json.dumps(answer.json())
    assert "components.hello.robot.image" in said and "may not pull" in said
    # A tag never pushed cannot be pinned either; nor can a local image that is not in the registry.
    api.force_authenticate(alice)
    answer = api.post("/api/releases", {"config": pinned_only(f"{own_registry.host}/alice/never:1")}, format="json")
    assert answer.status_code == 400 and "has no alice/never:1" in json.dumps(answer.json()), answer.content
    answer = api.post("/api/releases", {"config": config(f"{own_registry.host}/alice/pin:1", "pin")}, format="json")
    assert answer.status_code == 400, answer.content
    assert answer.json()["config"][0].startswith("components.base.robot.image: 'bridgeos/base:bookworm'")
    assert list(Release.objects.values_list("pk", flat=True)) == [release.pk]
