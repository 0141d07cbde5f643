"""A robot's own engine, behind the robot's shaped link, pulls a Skill's image it never saw; a cut pull resumes."""

from __future__ import annotations

import asyncio
import os
import ssl
import subprocess

import httpx
import pytest
from asgiref.sync import sync_to_async
from docker.api import APIClient

from benchmarks import _netshape as netshape
from bridgeos_agent.runtime.images import ImagePuller, RegistryLogin
from tests.net import engine as engines

from .conftest import make_fleet, pull_progress, tls_registry
from .layered import build_layered_image
from .test_docker_registry import PUSH_PROBE, run

pytestmark = [pytest.mark.docker, pytest.mark.django_db(transaction=True), pytest.mark.log_errors(PUSH_PROBE)]

LINK = netshape.Conditions(up_mbit=50, down_mbit=50, delay_ms=20)


class RobotSide:
    """The robot's network namespace behind a shaped link, and the robot's own Docker engine in it."""

    def __init__(self) -> None:
        self.link = netshape.Link(LINK).up()
        try:
            self.engine = engines.Engine(self.link.name, "robot", address=self.link.cloud_ip).start()
        except BaseException:
            self.link.down()
            raise

    def received(self) -> int:
        """Return the bytes that crossed the link into the robot, counted on its interface."""
        path = f"/sys/class/net/{self.link.cloud_device}/statistics/rx_bytes"
        return int(subprocess.run([*self.link.exec_prefix, "cat", path], capture_output=True, text=True).stdout)

    def cut(self) -> None:
        """Drop every packet both ways; no socket is told."""
        self.link.set(netshape.Conditions(up_mbit=50, down_mbit=50, delay_ms=20, loss_pct=100))

    def restore(self) -> None:
        self.link.set(LINK)

    def close(self) -> None:
        self.engine.close()
        self.link.down()


@pytest.fixture
def robot_side():
    reason = engines.available()
    if reason:
        pytest.skip(reason)
    side = RobotSide()
    yield side
    side.close()


@pytest.fixture
def fleet(daphne_server):
    return make_fleet()


@pytest.fixture
def registry_on_link(daphne_server, robot_side, tmp_path, settings):
    """A TLS registry on the host's end of the robot's link, the cloud's own (its images are pinned)."""
    with tls_registry(daphne_server, tmp_path / "registry", robot_side.link.host_ip) as registry:
        settings.BRIDGEOS = {
            **settings.BRIDGEOS,
            "REGISTRY_HOST": registry.host,
            "REGISTRY_CA": str(registry.ca_file),
        }
        yield registry


async def test_a_user_pushes_with_docker_and_a_robot_behind_its_link_pulls_and_runs_it(
    daphne_server, robot_side, registry_on_link, fleet, tmp_path
):
    from bridgeos_agent.controller import AgentSettings, RobotController
    from bridgeos_agent.link import Link
    from bridgeos_agent.protocol import Event
    from robots.models import Robot
    from skills.models import Component, Skill
    from skills.services import add_skill

    registry = registry_on_link
    ref = f"{registry.host}/alice/hello:1"
    local = await asyncio.to_thread(build_layered_image, tmp_path / "image", "bridgeos-test/hello-layers:1", 3, 500_000)
    env = {**os.environ, "DOCKER_CONFIG": str(tmp_path / "docker")}
    login = run(
        "docker", "login", registry.host, "-u", "alice", "--password-stdin", env=env, stdin=fleet.alice_token.secret
    )
    assert login.returncode == 0, login.stderr
    assert run("docker", "tag", local, ref).returncode == 0
    pushed = run("docker", "push", ref, env=env)
    assert pushed.returncode == 0, pushed.stderr + pushed.stdout
    run("docker", "rmi", local, ref)

    robot = fleet.alice_robot.name
    viewer = Link(daphne_server.ws_url + "/ws/client/")
    await viewer.connect(Event.AUTHENTICATION_CLIENT, {"token": fleet.alice_token.secret})
    settings = AgentSettings(
        master=daphne_server.ws_url,
        robot=robot,
        token=fleet.alice_robot.secret,
        data_dir=tmp_path / "agent",
        runtime="docker",
        runtime_options={"docker_url": robot_side.engine.url},
        ca_file=registry.ca_file,
        simulate=True,
        stop_components_on_exit=True,
    )
    controller = RobotController(settings)
    task = asyncio.create_task(controller.run())
    try:
        await asyncio.wait_for(controller.config_from_cloud.wait(), 20)
        skill = {
            "skill": "Hello",
            "skill_id": "hello",
            "components": {"hello": {"name": "Hello", "location": "robot", "robot": {"image": ref}}},
        }
        await sync_to_async(lambda: add_skill(Robot.objects.get(id=robot), skill))()
        pinned = await sync_to_async(lambda: Skill.objects.get(robot_id=robot, skill_id="hello").config)()
        image = pinned["components"]["hello"]["robot"]["image"]
        assert image.startswith(f"{ref}@sha256:"), image  # the tag kept for people, the digest for engines
        digest = image.partition("@")[2]
        headers = {"Authorization": f"Token {fleet.alice_token.secret}"}
        async with httpx.AsyncClient(base_url=daphne_server.url, headers=headers, timeout=90) as api:
            answer = await api.post(f"/api/robot/{robot}/skill/hello/start", params={"wait": 60})
        assert answer.status_code == 200, answer.text
        progress = await pull_progress(viewer, timeout=60)
        done = [p["done"] for p in progress]
        assert done == sorted(done), f"progress went backwards: {done}"
        manifest = await asyncio.to_thread(
            httpx.get,
            f"{registry.url}/v2/alice/hello/manifests/{digest}",
            headers={
                **registry_bearer(daphne_server, fleet.alice_token),
                "Accept": "application/vnd.docker.distribution.manifest.v2+json",
            },
            verify=ssl.create_default_context(cafile=str(registry.ca_file)),
        )
        manifest = manifest.json()
        size = manifest["config"]["size"] + sum(layer["size"] for layer in manifest["layers"])
        assert progress[-1]["total"] == size == progress[-1]["done"], (progress[-1], size)
        for _ in range(150):
            component = await sync_to_async(Component.objects.get)(skill__robot_id=robot, component_id="hello")
            if component.status == "running":
                break
            await asyncio.sleep(0.2)
        assert component.status == "running", component.message
        # It runs in the robot's engine, from exactly the pinned bytes.
        digests = robot_side.engine.docker("image", "inspect", "-f", "{{json .RepoDigests}}", image).stdout
        assert f"{registry.host}/alice/hello@{digest}" in digests
        assert run("docker", "image", "inspect", image).returncode != 0, "the machine's own engine pulled it"
    finally:
        controller.stop()
        await asyncio.wait_for(task, 30)
        await viewer.close()


def registry_bearer(daphne_server, who) -> dict[str, str]:
    from .conftest import bearer

    return bearer(daphne_server, who, "repository:alice/hello:pull")


async def test_a_pull_cut_by_the_link_resumes_without_fetching_the_complete_layers_again(
    daphne_server, robot_side, registry_on_link, fleet, tmp_path
):
    registry = registry_on_link
    local = await asyncio.to_thread(build_layered_image, tmp_path / "image", "bridgeos-test/cut-layers:1", 8, 1_000_000)
    pushed = registry.push(local, "alice/cut:1", fleet.alice_token)
    assert pushed.returncode == 0, pushed.stderr
    run("docker", "rmi", local)
    image = f"{registry.host}/alice/cut:1"
    api = APIClient(base_url=robot_side.engine.url, version="auto", timeout=120)

    async def call(function, *args, **kwargs):
        return await asyncio.to_thread(function, *args, **kwargs)

    login = RegistryLogin.for_cloud(
        daphne_server.url, fleet.alice_robot.name, fleet.alice_robot.secret, registry.ca_file
    )
    puller = ImagePuller(login, call)
    halfway = asyncio.Event()
    seen: list[tuple[int, int]] = []

    def progress(done: int, total: int) -> None:
        seen.append((done, total))
        if done >= total / 2:
            halfway.set()

    before = robot_side.received()
    pull = asyncio.ensure_future(puller.ensure(api, image, "component cut/hello", progress))
    await asyncio.wait_for(halfway.wait(), 60)
    robot_side.cut()
    await asyncio.sleep(8)
    assert not pull.done(), "the pull finished with the link cut"
    robot_side.restore()
    assert await asyncio.wait_for(pull, 120) is True
    total = seen[-1][1]
    crossed = robot_side.received() - before
    assert seen[-1][0] == total
    # Everything that crossed: the image once, what was in flight at the cut, and TCP/TLS's overhead.
    assert crossed <= 1.2 * total, f"{crossed} bytes crossed the link for an image of {total}"
    assert robot_side.engine.docker("image", "inspect", image, check=False).returncode == 0
