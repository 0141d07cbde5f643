"""The robot's Docker network follows the local subnet the cloud allocated (robot config subnets.local)."""

from __future__ import annotations

import random
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from docker.api import APIClient

from bridgeos_agent.runtime.docker import DockerRuntime
from tests.agent.test_runtime_docker import make_spec

pytestmark = [pytest.mark.docker, pytest.mark.timeout(120)]


@pytest.fixture
def api() -> Iterator[APIClient]:
    try:
        client = APIClient(version="auto", timeout=10)
        client.ping()
    except Exception:
        pytest.skip("dockerd is not running: sudo scripts/services.sh docker")
    yield client
    client.close()


@pytest.fixture
def robot(api: APIClient) -> Iterator[str]:
    robot = f"net{uuid.uuid4().hex[:8]}"
    yield robot
    for container in api.containers(all=True, filters={"label": f"io.bridgeos.robot={robot}"}):
        api.remove_container(container["Id"], force=True, v=True)
    for network in api.networks(names=[f"bridgeos-{robot}"]):
        api.remove_network(network["Id"])


def subnet_of(api: APIClient, robot: str) -> str:
    return api.inspect_network(f"bridgeos-{robot}")["IPAM"]["Config"][0]["Subnet"]


async def test_the_network_moves_to_a_new_subnet_once_no_component_uses_it(api, robot, tmp_path: Path):
    # Rarely used /24s of the local pool, so parallel runs on this machine do not collide.
    first, second, third = (f"10.{random.randint(72, 79)}.{random.randint(0, 255)}.0/24" for _ in range(3))
    runtime = DockerRuntime(robot, data_dir=tmp_path)
    try:
        runtime.use_subnet(first)
        await runtime.start(make_spec(robot, "detector"))
        assert subnet_of(api, robot) == first
        await runtime.stop("people", "detector")
        runtime.use_subnet(second)
        await runtime.start(make_spec(robot, "detector"))
        assert subnet_of(api, robot) == second
        # A component still uses the network: it stays, and launches go on working.
        runtime.use_subnet(third)
        await runtime.start(make_spec(robot, "sampler"))
        assert subnet_of(api, robot) == second
    finally:
        await runtime.close(stop_components=True)
