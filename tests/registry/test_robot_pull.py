"""A robot's Docker runtime pulls the images it lacks from the cloud's registry, with a token its own cloud grants."""

from __future__ import annotations

import asyncio
import secrets
import shutil
import subprocess
import tarfile
from pathlib import Path
from typing import Any

import httpx
import pytest
from django.core.management import call_command
from docker.api import APIClient

from bridgeos_agent.imagerefs import split_reference
from bridgeos_agent.runtime import ComponentSpec, RuntimeFailure
from bridgeos_agent.runtime.docker import DockerRuntime
from bridgeos_agent.runtime.images import DiskFull, ImagePuller, RegistryLogin
from bridgeos_agent.skillconfig import ComponentResources, LaunchSpec
from tests.conftest import free_port

from .conftest import make_fleet, pull_progress, serving
from .test_docker_registry import PUSH_PROBE, push, run

pytestmark = [pytest.mark.docker, pytest.mark.django_db(transaction=True), pytest.mark.log_errors(PUSH_PROBE)]


@pytest.fixture
def published(registry, fleet, tmp_path):
    """Return a function that pushes a new small runnable image as Alice and leaves no layer of it in the engine."""

    def publish(target: str) -> str:
        base = tmp_path / target.replace("/", "_").replace(":", "_")
        base.mkdir()
        (base / "run.txt").write_text(secrets.token_hex(16))  # a layer no engine has seen
        libs = subprocess.run(["ldd", "/bin/sleep"], capture_output=True, text=True, check=True).stdout
        files = ["/bin/sleep"] + [part for part in libs.split() if part.startswith("/")]
        with tarfile.open(base / "rootfs.tar", "w") as tar:
            for path in files:
                tar.add(Path(path).resolve(), arcname=path.lstrip("/"))
            tar.add(base / "run.txt", arcname="run.txt")
        local = f"bridgeos-test/sleeper:{secrets.token_hex(4)}"
        done = run("docker", "import", str(base / "rootfs.tar"), local)
        assert done.returncode == 0, done.stderr
        try:
            pushed = push(registry, local, target, fleet.alice_token)
            assert pushed.returncode == 0, pushed.stderr
        finally:
            run("docker", "rmi", "-f", local)
        return f"{registry.host}/{target}"

    return publish


@pytest.fixture
def fleet(daphne_server):
    """Alice, Bob and their robots (made outside the event loop: the tests are async)."""
    return make_fleet()


def docker_agent(daphne_server, fleet, tmp_path) -> Any:
    """The settings of Alice's robot's agent on the Docker runtime (simulated sensors), stopping its components at exit."""
    from bridgeos_agent.controller import AgentSettings

    return AgentSettings(
        master=daphne_server.ws_url,
        robot=fleet.alice_robot.name,
        token=fleet.alice_robot.secret,
        data_dir=tmp_path / "agent",
        runtime="docker",
        simulate=True,
        stop_components_on_exit=True,
    )


def spec(robot: str, image: str, component: str = "hello") -> ComponentSpec:
    """Build the spec the controller would give a component of this image."""
    return ComponentSpec(
        robot=robot,
        skill="pull",
        component=component,
        location="robot",
        launch=LaunchSpec(image=image, command=["/bin/sleep", "600"]),
        resources=ComponentResources(),
        env={},
    )


def remove_robot_objects(robot: str) -> None:
    """Remove the containers and network a runtime made for a robot."""
    api = APIClient(version="auto", timeout=30)
    for container in api.containers(all=True, filters={"label": f"io.bridgeos.robot={robot}"}):
        api.remove_container(container["Id"], force=True, v=True)
    for network in api.networks(names=[f"bridgeos-{robot}"]):
        api.remove_network(network["Id"])


async def started(runtime: DockerRuntime, component: ComponentSpec) -> None:
    """Start a component and wait until Docker runs it."""
    await runtime.start(component)
    api = APIClient(version="auto", timeout=30)
    for _ in range(100):
        found = api.containers(filters={"name": runtime.container_name(component.skill, component.component)})
        if found and found[0]["State"] == "running":
            return
        await asyncio.sleep(0.1)
    raise AssertionError("the component's container never ran")


def test_image_references_are_split_as_docker_reads_them():
    assert split_reference("127.0.0.1:5000/alice/hello:1") == ("127.0.0.1:5000", "alice/hello", "1")
    assert split_reference("reg.example/alice/hello@sha256:ab") == ("reg.example", "alice/hello", "sha256:ab")
    assert split_reference("localhost/x") == ("localhost", "x", "latest")
    assert split_reference("alice/detector:1.2") == (None, "alice/detector", "1.2")
    assert split_reference("bridgeos/base:bookworm") == (None, "bridgeos/base", "bookworm")
    assert split_reference("reg:5000/a/b:t@sha256:cd") == ("reg:5000", "a/b", "sha256:cd")


def test_a_robot_sends_its_credentials_only_to_the_cloud_it_connects_to():
    login = RegistryLogin.for_cloud("wss://cloud.example:8443", "r1", "brt_x")
    assert login.cloud == "https://cloud.example:8443"
    assert login.owns("https://cloud.example:8443/api/registry/token")
    assert not login.owns("http://cloud.example:8443/api/registry/token")  # not downgraded to plain HTTP
    assert not login.owns("https://cloud.example.evil:8443/api/registry/token")
    assert RegistryLogin.for_cloud("ws://127.0.0.1:8000", "r1", "t").cloud == "http://127.0.0.1:8000"


async def test_a_robot_pulls_its_owners_image_it_never_had_and_runs_it(daphne_server, published, fleet, tmp_path):
    image = published("alice/sleeper:1")
    login = RegistryLogin.for_cloud(daphne_server.url, fleet.alice_robot.name, fleet.alice_robot.secret)
    runtime = DockerRuntime(fleet.alice_robot.name, data_dir=tmp_path, registry=login)
    seen: list[tuple[int, int]] = []
    runtime.on_pull = lambda skill, component, image: lambda done, total: seen.append((done, total))
    try:
        await started(runtime, spec(fleet.alice_robot.name, image))
        assert runtime.images.bytes_pulled > 0
        assert seen and seen[-1][0] == seen[-1][1] > 0, seen
        assert [done for done, _ in seen] == sorted(done for done, _ in seen), "progress went backwards"
        # A second component of the image starts from the robot's copy without pulling again.
        before = runtime.images.bytes_pulled
        await started(runtime, spec(fleet.alice_robot.name, image, "again"))
        assert runtime.images.bytes_pulled == before
    finally:
        await runtime.close(stop_components=True)
        remove_robot_objects(fleet.alice_robot.name)
        run("docker", "rmi", "-f", image)


async def test_a_robot_cannot_pull_another_owners_image_nor_send_its_token_elsewhere(
    daphne_server, published, fleet, tmp_path
):
    image = published("alice/sleeper:2")
    api = APIClient(version="auto", timeout=30)

    async def call(function, *args, **kwargs):
        return await asyncio.to_thread(function, *args, **kwargs)

    bob = ImagePuller(RegistryLogin.for_cloud(daphne_server.url, fleet.bob_robot.name, fleet.bob_robot.secret), call)
    with pytest.raises(RuntimeFailure, match="refused"):
        await bob.ensure(api, image, "component pull/hello")
    stranger = ImagePuller(RegistryLogin("alice-bot", fleet.alice_robot.secret, "http://127.0.0.1:9"), call)
    with pytest.raises(RuntimeFailure, match="not to this robot's cloud"):
        await stranger.ensure(api, image, "component pull/hello")
    nameless = ImagePuller(None, call)
    with pytest.raises(RuntimeFailure, match="names no registry"):
        await nameless.ensure(api, "alice/never-built:1", "component pull/hello")
    assert bob.bytes_pulled == stranger.bytes_pulled == 0
    assert run("docker", "image", "inspect", image).returncode != 0, "a refused pull left the image behind"


async def test_a_pull_the_disk_cannot_hold_is_refused_as_disk_full_and_a_local_image_needs_no_registry(
    daphne_server, published, fleet, tmp_path
):
    image = published("alice/sleeper:3")
    api = APIClient(version="auto", timeout=30)

    async def call(function, *args, **kwargs):
        return await asyncio.to_thread(function, *args, **kwargs)

    login = RegistryLogin.for_cloud(daphne_server.url, fleet.alice_robot.name, fleet.alice_robot.secret)
    free = shutil.disk_usage(api.info()["DockerRootDir"]).free
    crowded = ImagePuller(login, call, disk_reserve=free)
    with pytest.raises(DiskFull, match=r"disk_full: image .* needs about \d+ MiB .* MiB free"):
        await crowded.ensure(api, image, "component pull/hello")
    assert run("docker", "image", "inspect", image).returncode != 0
    try:
        assert await ImagePuller(login, call).ensure(api, image, "component pull/hello") is True
        # Now local: a robot whose cloud and registry are out of reach starts it all the same.
        offline = ImagePuller(RegistryLogin("alice-bot", "x", "http://127.0.0.1:9"), call)
        assert await offline.ensure(api, image, "component pull/hello") is False
    finally:
        run("docker", "rmi", "-f", image)


async def test_an_agent_pulls_a_skills_image_as_it_is_added_tells_the_cloud_how_far_it_is_and_runs_it(
    daphne_server, published, fleet, tmp_path
):
    from asgiref.sync import sync_to_async

    from bridgeos_agent.controller import RobotController
    from bridgeos_agent.link import Link
    from bridgeos_agent.protocol import Event
    from robots.models import Robot
    from skills.models import Component
    from skills.services import add_skill

    image = published("alice/agent:1")
    robot = fleet.alice_robot.name
    launch = {"image": image, "command": ["/bin/sleep", "600"]}
    skill = {
        "skill": "Pull",
        "skill_id": "pull",
        "components": {"hello": {"name": "Hello", "location": "robot", "robot": launch}},
    }
    viewer = Link(daphne_server.ws_url + "/ws/client/")
    await viewer.connect(Event.AUTHENTICATION_CLIENT, {"token": fleet.alice_token.secret})
    controller = RobotController(docker_agent(daphne_server, fleet, tmp_path))
    task = asyncio.create_task(controller.run())
    try:
        await asyncio.wait_for(controller.config_from_cloud.wait(), 20)
        await sync_to_async(lambda: add_skill(Robot.objects.get(id=robot), skill))()
        # Added, not started: the robot pulls the image ahead, so the start will not wait for bytes.
        for _ in range(150):  # the engine lists the image once the pull has ended; its bytes are counted then
            if (
                run("docker", "image", "inspect", image).returncode == 0
                and controller.metrics.image_bytes[("pull", "hello")] > 0
            ):
                break
            await asyncio.sleep(0.2)
        else:
            raise AssertionError("the robot did not pull the image of the Skill it was told of")
        headers = {"Authorization": f"Token {fleet.alice_token.secret}"}
        async with httpx.AsyncClient(base_url=daphne_server.url, headers=headers, timeout=60) as api:
            answer = await api.post(f"/api/robot/{robot}/skill/pull/start", params={"wait": 30})
        assert answer.status_code == 200, answer.text
        progress = await pull_progress(viewer, timeout=30)
        assert progress[-1]["image"] == image and progress[-1]["total"] > 0
        for _ in range(100):
            component = await sync_to_async(Component.objects.get)(skill__robot_id=robot, component_id="hello")
            if component.status == "running":
                break
            await asyncio.sleep(0.2)
        assert component.status == "running", component.message
        assert controller.metrics.image_bytes[("pull", "hello")] > 0
    finally:
        controller.stop()
        await asyncio.wait_for(task, 30)
        await viewer.close()
        remove_robot_objects(robot)
        run("docker", "rmi", "-f", image)


async def test_a_pull_whose_registry_is_out_of_reach_is_tried_again_until_it_answers(
    daphne_server, registry, published, fleet, tmp_path
):
    image = published("alice/sleeper:4")
    # A second registry on the first one's storage, on a port nothing listens on yet.
    host = f"127.0.0.1:{free_port()}"
    storage = registry.log.parent / "storage"
    call_command(
        "registry_config", realm=registry.realm, listen=host, storage=str(storage), out=str(tmp_path), stdout=None
    )
    moved = image.replace(registry.host, host)
    api = APIClient(version="auto", timeout=30)

    async def call(function, *args, **kwargs):
        return await asyncio.to_thread(function, *args, **kwargs)

    login = RegistryLogin.for_cloud(daphne_server.url, fleet.alice_robot.name, fleet.alice_robot.secret)
    puller = ImagePuller(login, call)
    pull = asyncio.ensure_future(puller.ensure(api, moved, "component pull/hello"))
    try:
        await asyncio.sleep(1.5)
        assert not pull.done(), "a pull from a registry out of reach ended at once"
        with serving(tmp_path / "config.yml", host, tmp_path / "registry.log"):
            assert await asyncio.wait_for(pull, 60) is True
        assert puller.pulls_cut >= 1
        assert run("docker", "image", "inspect", moved).returncode == 0
    finally:
        pull.cancel()
        run("docker", "rmi", "-f", moved)
