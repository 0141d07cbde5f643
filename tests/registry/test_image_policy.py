"""A robot removes the pulled images no Skill uses, keeping the newest of each repository."""

from __future__ import annotations

import asyncio

import pytest
from docker.api import APIClient

from bridgeos_agent.runtime.images import ImagePuller, RegistryLogin, unused_images

from .test_docker_registry import PUSH_PROBE, run
from .test_robot_pull import fleet, published  # noqa: F401  (fixtures)


def image(image_id: str, created: int, *names: str) -> dict:
    """Describe an image as the Engine API lists it."""
    return {
        "Id": image_id,
        "Created": created,
        "RepoTags": [n for n in names if "@" not in n],
        "RepoDigests": [n for n in names if "@" in n],
    }


def test_the_newest_images_of_each_repository_stay_and_those_in_use_too():
    images = [
        image("a1", 1, "reg:5000/alice/a:1", "reg:5000/alice/a@sha256:11"),
        image("a2", 2, "reg:5000/alice/a@sha256:22"),
        image("a3", 3, "reg:5000/alice/a:3"),
        image("a4", 4, "reg:5000/alice/a:4"),
        image("b1", 1, "reg:5000/bob/b:1"),
        image("local", 0, "bridgeos/ros:noetic"),  # built here, never a registry's: never removed
        image("dangling", 0, "<none>:<none>"),
    ]
    assert unused_images(images, used=set(), keep=2) == ["a1", "a2"]
    assert unused_images(images, used={"a4"}, keep=2) == ["a1"]  # a4 in use: a3 and a2 are the newest spare
    assert unused_images(images, used=set(), keep=1) == ["a1", "a2", "a3"]
    assert unused_images(images, used=set(), keep=10) == []
    # An image in two repositories stays while either keeps it: a1 is carol's newest.
    shared = [image("a1", 1, "reg:5000/alice/a:1", "reg:5000/carol/c:1"), *images[1:]]
    assert unused_images(shared, used=set(), keep=2) == ["a2"]


@pytest.mark.docker
@pytest.mark.django_db(transaction=True)
@pytest.mark.log_errors(PUSH_PROBE)
async def test_a_robot_keeps_the_newest_pulls_of_a_repository_and_every_image_a_skill_names(
    daphne_server,
    published,  # noqa: F811
    fleet,  # noqa: F811
):
    versions = []
    for n in range(1, 5):
        if versions:
            await asyncio.sleep(1.1)  # an image's creation time counts in seconds: one version a second
        versions.append(published(f"alice/kept:{n}"))
    api = APIClient(version="auto", timeout=30)

    async def call(function, *args, **kwargs):
        return await asyncio.to_thread(function, *args, **kwargs)

    login = RegistryLogin.for_cloud(daphne_server.url, fleet.alice_robot.name, fleet.alice_robot.secret)
    puller = ImagePuller(login, call, keep=2)
    puller.in_use = lambda: {versions[0]}  # a Skill of the robot still names the first version
    try:
        for version in versions:
            assert await puller.ensure(api, version, "component kept/hello") is True
        present = [run("docker", "image", "inspect", v).returncode == 0 for v in versions]
        assert present == [True, False, True, True], present
    finally:
        for version in versions:
            run("docker", "rmi", "-f", version)
