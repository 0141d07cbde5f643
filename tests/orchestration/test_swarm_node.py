"""A cloud copy runs on a second Swarm node that never had its image: Swarm carries the cloud's pull token there.

The node is a real dockerd in a network namespace, joined to this machine's Swarm as a worker,
with an empty image store; the registry serves TLS on this machine's end of the node's link,
with a certificate both engines trust through certs.d, and takes its tokens from the test
daphne. Alice pushes an image, adds a Skill whose cloud copy is constrained to the node, and
the cloud's launch spec (pinned digest and registry auth) is handed to the Swarm runtime.
"""

from __future__ import annotations

import asyncio
import base64
import dataclasses
import json
import re
import secrets
import subprocess
from datetime import UTC, datetime, timedelta

import pytest
from django.conf import settings as django_settings

import docker
from bridgeos_agent.runtime.base import Status
from robots.models import Robot
from skills.cloud.orchestration import LaunchFailed, cloud_spec
from skills.cloud.swarm import SwarmRuntime
from skills.cloud.swarmauth import PullRefused, encode_auth, registry_auth
from skills.cloud.swarmspec import task_key
from skills.models import CloudInstance, Component
from skills.services import add_skill
from tests.net import engine as second_engine
from tests.net.swarmnode import SwarmNode, swarm_node
from tests.registry.conftest import ask_token, make_fleet, tls_registry
from tests.registry.layered import build_layered_image
from tests.registry.test_docker_registry import PUSH_PROBE

pytestmark = [
    pytest.mark.docker,
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(240),
    pytest.mark.log_errors(PUSH_PROBE),  # the node's refused pulls the registry logs as warnings only
]

SKILL = "far"
START_TIMEOUT_S = 60.0


@pytest.fixture(scope="module")
def swarm_worker() -> SwarmNode:
    """A worker node of this machine's Swarm in its own namespace, with an empty image store."""
    reason = second_engine.available()
    if reason:
        pytest.skip(f"no second engine: {reason}")
    if subprocess.run(["docker", "node", "ls"], capture_output=True).returncode != 0:
        pytest.skip("this machine's engine is no Swarm manager: bash scripts/services.sh docker")
    with swarm_node("node") as node:
        yield node


@pytest.fixture
def node_registry(daphne_server, swarm_worker, tmp_path, settings):
    """The cloud's registry, serving TLS where the node reaches this machine, made the cloud's own."""
    with tls_registry(daphne_server, tmp_path / "registry", swarm_worker.host_address) as registry:
        settings.BRIDGEOS = {
            **settings.BRIDGEOS,
            "REGISTRY_HOST": registry.host,
            "REGISTRY_CA": str(registry.ca_file),
            "CLOUD_RUNTIME": "swarm",
        }
        yield registry


@pytest.fixture
def publish(node_registry, tmp_path):
    """Return a function that pushes a new image as Alice and leaves none of it in this machine's engine."""

    def push(target: str, who) -> str:
        local = f"bridgeos-test/node:{secrets.token_hex(4)}"
        build_layered_image(tmp_path / local.rpartition(":")[2], local, 1, 4096)
        try:
            done = node_registry.push(local, target, who)
            assert done.returncode == 0, done.stderr
        finally:
            subprocess.run(["docker", "rmi", "-f", local], capture_output=True)
        return f"{node_registry.host}/{target}"

    return push


def skill_config(image: str, node_id: str) -> dict:
    """Return a Skill of one cloud component running ``image``, constrained to one Swarm node."""
    launch = {"image": image, "command": ["/bin/sleep", "600"], "placement": [f"node.id=={node_id}"]}
    component = {"name": "Far", "location": "cloud", "ros": False, "cloud": launch}
    return {"skill": "Far", "skill_id": SKILL, "components": {"far": component}}


def launch_spec(robot: Robot, config: dict):
    """Add the Skill as the API does (pinning its image) and return the cloud's launch spec of its copy."""
    add_skill(robot, config)
    component = Component.objects.get(skill__robot=robot, skill__skill_id=SKILL, component_id="far")
    instance = CloudInstance.objects.create(component=component, desired="running", token="t0", runtime="swarm")
    return cloud_spec(instance)


def run_on_swarm(robot_id: str, operation):
    """Run ``operation(runtime)`` on a Swarm runtime of the robot; remove the robot's services and network afterwards."""

    async def main():
        runtime = SwarmRuntime(robot_id, data_dir=django_settings.DATA_DIR / "cloud" / "runtime")
        try:
            return await operation(runtime)
        finally:
            await remove_all(runtime)

    return asyncio.run(main())


async def remove_all(runtime: SwarmRuntime) -> None:
    """Remove the robot's services, then its network once Swarm has detached them from it, then close."""
    try:
        for item in await runtime.observe():
            if item.robot == runtime.robot:
                await runtime.remove(item)
        for _ in range(100):
            await runtime.remove_network()
            if runtime.network not in (await runtime.networks()).values():
                break
            await asyncio.sleep(0.2)
    finally:
        await runtime.close()


def start_and_wait(node: SwarmNode, spec):
    """Create the copy's service, wait until its task runs or fails; return its state, node and inspected service."""

    async def operation(runtime: SwarmRuntime):
        await placed(node, runtime, runtime.start(spec))
        state = await runtime.wait_running(spec.skill, spec.component, START_TIMEOUT_S)
        name = runtime.service_name(spec.skill, spec.component)
        return state, node_of(name), docker.APIClient(version="auto").inspect_service(name)

    return run_on_swarm(spec.robot, operation)


async def placed(node: SwarmNode, runtime: SwarmRuntime, action) -> None:
    """Await a create or restart with the node taking new tasks, until the copy's new task has a node."""
    with node.accepting():
        state = await action
        name = runtime.service_name(state.skill, state.component)
        for _ in range(300):
            if node_of(name):
                return
            await asyncio.sleep(0.1)
    raise AssertionError(f"Swarm placed no task of {name} within 30 s")


def node_of(service: str) -> str:
    """Return the node the service's newest task was placed on (empty: not placed yet)."""
    tasks = docker.APIClient(version="auto").tasks(filters={"service": service})
    return max(tasks, key=task_key).get("NodeID", "") if tasks else ""


def node_digests(node: SwarmNode) -> list[str]:
    """List every repo@digest the node's engine holds."""
    listed = node.engine.docker("image", "ls", "--digests", "--format", "{{json .}}").stdout.splitlines()
    return [f"{row['Repository']}@{row['Digest']}" for row in map(json.loads, listed) if row["Digest"] != "<none>"]


def test_a_cloud_copy_runs_on_a_node_that_never_had_its_image_only_with_the_token_swarm_carries(
    swarm_worker, node_registry, publish, daphne_server
):
    fleet = make_fleet()
    image = publish("alice/far:1", fleet.alice_token)
    robot = Robot.objects.get(id=fleet.alice_robot.name)
    spec = launch_spec(robot, skill_config(image, swarm_worker.node_id))
    # The copy runs the digest the Skill was pinned to when it was added, not the tag.
    assert re.fullmatch(rf"{re.escape(image)}@sha256:[0-9a-f]{{64}}", spec.launch.image), spec.launch.image
    assert spec.registry_auth and spec.registry_auth not in repr(spec)
    repository_digest = f"{node_registry.host}/alice/far@{spec.launch.image.rpartition('@')[2]}"
    assert node_digests(swarm_worker) == []

    # Without registry credentials, and with the token Bob gets for Alice's repository, the node
    # cannot pull: Swarm rejects the task there (it has no such image).
    bob_token = ask_token(daphne_server, fleet.bob_token, "repository:alice/far:pull")
    assert bob_token.status_code == 200 and bob_token.json()["token"], bob_token.text
    bobs = encode_auth(bob_token.json()["token"], node_registry.host)
    for auth in ("", bobs):
        state, node, _ = start_and_wait(swarm_worker, dataclasses.replace(spec, registry_auth=auth))
        assert node == swarm_worker.node_id
        assert state.status is Status.FAILED, state
        assert re.search(r"No such image|unauthorized|denied", state.message or ""), state.message
    assert node_digests(swarm_worker) == []

    # With the cloud's token for Alice it runs there, from the pinned digest the node pulled.
    state, node, service = start_and_wait(swarm_worker, spec)
    assert state.status is Status.RUNNING, state.message
    assert node == swarm_worker.node_id
    token = json.loads(base64.urlsafe_b64decode(spec.registry_auth))["registrytoken"]
    assert token not in json.dumps(service), "the Engine API shows the service's pull token"
    assert node_digests(swarm_worker) == [repository_digest]
    here = subprocess.run(["docker", "image", "inspect", spec.launch.image], capture_output=True)
    assert here.returncode != 0, "this machine's engine pulled the image: the node should have, alone"


def test_a_restarted_copy_gets_a_fresh_token_where_the_one_it_was_created_with_expired(
    swarm_worker, node_registry, publish
):
    fleet = make_fleet()
    image = publish("alice/later:1", fleet.alice_token)
    robot = Robot.objects.get(id=fleet.alice_robot.name)
    spec = launch_spec(robot, skill_config(image, swarm_worker.node_id))
    # A token minted long enough ago that the registry refuses it (exp has a minute's leeway).
    ttl = django_settings.BRIDGEOS["REGISTRY_SWARM_TOKEN_S"]
    past = datetime.now(UTC) - timedelta(seconds=ttl + 120)
    expired = dataclasses.replace(spec, registry_auth=registry_auth(spec.launch.image, robot.owner, now=past))

    async def operation(runtime: SwarmRuntime):
        await placed(swarm_worker, runtime, runtime.start(expired))
        refused = await runtime.wait_running(SKILL, "far", START_TIMEOUT_S)
        # An update without registry auth keeps the token Swarm has: expired, so refused again.
        await placed(swarm_worker, runtime, runtime.restart(dataclasses.replace(spec, registry_auth="")))
        kept = await runtime.wait_running(SKILL, "far", START_TIMEOUT_S)
        await placed(swarm_worker, runtime, runtime.restart(spec))  # as the cloud builds it now: a fresh token
        return refused, kept, await runtime.wait_running(SKILL, "far", START_TIMEOUT_S)

    refused, kept, state = run_on_swarm(robot.id, operation)
    for failed in (refused, kept):
        assert failed.status is Status.FAILED and re.search(r"No such image|unauthorized", failed.message or "")
    assert kept.pid_or_container_id != refused.pid_or_container_id, "the restart made no new task"
    assert state.status is Status.RUNNING, state.message
    assert any(digest.endswith(spec.launch.image.rpartition("@")[2]) for digest in node_digests(swarm_worker))


def test_only_images_of_the_cloud_registry_get_its_token_and_only_pinned_and_pullable_ones_launch(settings):
    from skills.models import Skill

    host = "registry.test:5000"
    settings.BRIDGEOS = {**settings.BRIDGEOS, "REGISTRY_HOST": host}
    fleet = make_fleet()
    robot = Robot.objects.get(id=fleet.alice_robot.name)
    bob = Robot.objects.get(id=fleet.bob_robot.name).owner
    assert registry_auth("bridgeos/base:bookworm", robot.owner) == ""
    assert registry_auth(f"other.example:5000/alice/x@sha256:{'0' * 64}", robot.owner) == ""
    mine = f"{host}/alice/x@sha256:{'0' * 64}"
    document = json.loads(base64.urlsafe_b64decode(registry_auth(mine, robot.owner)))
    assert document["serveraddress"] == host and document["registrytoken"].count(".") == 2
    with pytest.raises(PullRefused, match="'bob' may not pull 'alice/x'"):
        registry_auth(mine, bob)
    # A Skill stored with an unpinned image of the cloud's registry (not added through add_skill) does not launch.
    skill = Skill.objects.create(robot=robot, skill_id=SKILL, name="Far", config=skill_config(f"{host}/alice/x:1", "n"))
    component = Component.objects.create(skill=skill, component_id="far", location="cloud")
    instance = CloudInstance.objects.create(component=component, desired="running", token="t1")
    with pytest.raises(LaunchFailed, match="is not pinned by digest"):
        cloud_spec(instance)
