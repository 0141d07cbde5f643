"""Cloud copies' output from Docker: a container's and a Swarm service's lines, both streams, Docker's timestamps."""

from __future__ import annotations

import time

import pytest

import docker
from logs.collector import collect_copy
from logs.models import ComponentLog
from skills.cloud.runtime import labels, object_name
from tests.conftest import wait_until

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.docker]

IMAGE = "bridgeos/base:bookworm"
SCRIPT = "echo '[INFO] up'; sleep 0.2; echo 'ERROR: no camera' >&2; sleep 0.2; echo second; sleep 300"


@pytest.fixture
def engine():
    try:
        client = docker.from_env(timeout=30)
        client.images.get(IMAGE)
    except docker.errors.DockerException as exc:
        pytest.skip(f"no dockerd with {IMAGE}: {exc}")
    yield client
    client.close()


def stored(robot: str) -> list[tuple[int, str, str, str | None]]:
    rows = ComponentLog.objects.filter(robot_id=robot, location="cloud").order_by("seq")
    return [(row.seq, row.stream, row.text, row.level_name) for row in rows]


@pytest.mark.parametrize("kind", ["docker", "swarm"])
def test_a_copys_docker_output_is_collected_with_both_streams_once(engine, kind):
    robot, skill, component = f"ld-{kind}", "people-detection", "detector"
    name = object_name(robot, skill, component)
    started = time.time()
    if kind == "docker":
        made = engine.containers.run(
            IMAGE, ["sh", "-c", SCRIPT], name=name, labels=labels(robot, skill, component), detach=True
        )
        remove = lambda: made.remove(force=True)  # noqa: E731
    else:
        made = engine.services.create(IMAGE, ["sh", "-c", SCRIPT], name=name, labels=labels(robot, skill, component))
        remove = made.remove
    try:
        wait_until(
            lambda: collect_copy(kind, robot, skill, component) or len(stored(robot)) >= 3, timeout=60, what="lines"
        )
        # Collected round after round, as beat does, until the copy has printed its three lines.
        wait_until(lambda: collect_copy(kind, robot, skill, component) >= 0 and len(stored(robot)) >= 3, timeout=60)
        collect_copy(kind, robot, skill, component)  # a round with nothing new stores nothing
        rows = stored(robot)
        assert [(seq, stream, text) for seq, stream, text, _ in rows] == [
            (1, "stdout", "[INFO] up"),
            (2, "stderr", "ERROR: no camera"),
            (3, "stdout", "second"),
        ]
        assert [level for *_, level in rows] == ["info", "error", None]
        times = list(ComponentLog.objects.filter(robot_id=robot).order_by("seq").values_list("ts", flat=True))
        assert started - 5 < times[0].timestamp() <= times[2].timestamp() < time.time()
    finally:
        remove()
