"""The registry tells the cloud of every tag pushed; the Robot API lists a user's repositories with their digests."""

from __future__ import annotations

import time

import httpx
import pytest

from registry.models import RegistryTag
from registry.notifications import tag_pushes

from .conftest import make_fleet
from .test_docker_registry import PUSH_PROBE, push, run

pytestmark = [pytest.mark.docker, pytest.mark.django_db(transaction=True), pytest.mark.log_errors(PUSH_PROBE)]

MANIFEST = "application/vnd.docker.distribution.manifest.v2+json"


def event(action: str, media_type: str, **target) -> dict:
    """Build one event of Distribution's notification envelope."""
    return {
        "action": action,
        "timestamp": "2026-12-02T10:00:00.123456789Z",
        "target": {"mediaType": media_type, "repository": "alice/hello", "digest": "sha256:" + "a" * 64, **target},
        "actor": {"name": "alice"},
    }


def test_only_manifest_pushes_with_a_tag_are_read_from_an_envelope():
    envelope = {
        "events": [
            event("push", MANIFEST, tag="1", size=528),
            event("push", "application/octet-stream"),  # a layer
            event("pull", MANIFEST, tag="1"),
            event("push", MANIFEST),  # pushed by digest: no tag
            event("push", MANIFEST, tag="2", digest="md5:x"),
            "junk",
        ]
    }
    pushes = tag_pushes(envelope)
    assert [(p.repository, p.tag, p.size, p.actor) for p in pushes] == [("alice/hello", "1", 528, "alice")]
    assert pushes[0].at.microsecond == 123456
    assert tag_pushes({"events": "nope"}) == tag_pushes([]) == tag_pushes(None) == []


def listing(daphne_server, token: str, **params) -> httpx.Response:
    """Ask the Robot API for the repositories a token's user may pull."""
    return httpx.get(
        f"{daphne_server.url}/api/registry/repositories",
        params=params,
        headers={"Authorization": f"Token {token}"},
        timeout=10,
    )


def test_a_push_is_listed_to_its_owner_with_its_digest_and_to_nobody_else(daphne_server, registry, tiny_image):
    fleet = make_fleet()
    assert push(registry, tiny_image, "alice/told:1", fleet.alice_token).returncode == 0
    digest = run(
        "skopeo", "inspect", "--tls-verify=false", "--creds", fleet.alice_token.creds,
        "--format", "{{.Digest}}", f"docker://{registry.host}/alice/told:1",
    ).stdout.strip()  # fmt: skip
    deadline = time.monotonic() + 20  # the registry tells the cloud from a queue of its own
    while not RegistryTag.objects.filter(repository="alice/told", tag="1").exists():
        assert time.monotonic() < deadline, "the registry never told the cloud of the push"
        time.sleep(0.2)

    mine = listing(daphne_server, fleet.alice_token.secret)
    assert mine.status_code == 200, mine.text
    assert mine.json() == [
        {
            "repository": "alice/told",
            "namespace": "alice",
            "tags": [
                {
                    "tag": "1",
                    "digest": digest,
                    "size": mine.json()[0]["tags"][0]["size"],
                    "pushed_by": "alice",
                    "pushed_at": mine.json()[0]["tags"][0]["pushed_at"],
                }
            ],
        }
    ]
    assert mine.json()[0]["tags"][0]["size"] > 0
    assert listing(daphne_server, fleet.bob_token.secret).json() == []
    assert listing(daphne_server, fleet.bob_token.secret, namespace="alice").json() == []
    assert [r["repository"] for r in listing(daphne_server, fleet.ops_token.secret).json()] == ["alice/told"]
    assert httpx.get(f"{daphne_server.url}/api/registry/repositories", timeout=10).status_code in (401, 403)


def test_notifications_without_the_registrys_token_change_nothing(daphne_server):
    envelope = {"events": [event("push", MANIFEST, tag="forged")]}
    for headers in ({}, {"Authorization": "Bearer nope"}):
        answer = httpx.post(f"{daphne_server.url}/api/registry/events", json=envelope, headers=headers, timeout=10)
        assert answer.status_code in (401, 403), answer.text
    assert not RegistryTag.objects.exists()


def test_the_images_page_shows_a_users_own_tags_with_their_digests_and_how_to_push(settings, client):
    from datetime import UTC, datetime

    from django.contrib.auth import get_user_model

    settings.BRIDGEOS = {**settings.BRIDGEOS, "REGISTRY_HOST": "127.0.0.1:5000"}
    users = get_user_model().objects
    alice, bob = users.create_user("alice"), users.create_user("bob")
    digest = "sha256:" + "b" * 64
    for repository, owner in (("alice/detector", "alice"), ("bob/secret", "bob")):
        RegistryTag.objects.create(
            repository=repository,
            namespace=owner,
            tag="1.2",
            digest=digest,
            size=2048,
            pushed_by=owner,
            pushed_at=datetime(2026, 12, 2, 10, tzinfo=UTC),
        )
    client.force_login(alice)
    page = client.get("/images/").content.decode()
    assert 'data-image="alice/detector:1.2"' in page and "bob/secret" not in page
    assert f'title="{digest}"' in page and "docker push 127.0.0.1:5000/alice/my-component:1" in page
    client.force_login(bob)
    assert "alice/detector" not in client.get("/images/").content.decode()
    client.logout()
    assert client.get("/images/").status_code == 302  # to the login page
