"""Share fixtures and helpers for the agent package's tests: a cloud of their own, robots and running agents."""

from __future__ import annotations

import asyncio
import contextlib
import copy
import json
import subprocess
from collections.abc import AsyncIterator, Iterator, Mapping
from importlib import resources
from pathlib import Path
from typing import Any

import psutil
import pytest
from asgiref.sync import sync_to_async

from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.monitor import SimulatedRobot
from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_agent.supervisor import SkillPlugin
from robots.services import create_robot, issue_api_token, update_robot_config
from skills.services import add_skill
from tests.agent.roshelpers import Nodes, private_rosmaster
from tests.conftest import BIN, ROOT, free_port, service_env, wait_for_port
from tests.logguard import watch

_SAMPLE = json.loads(
    resources.files("bridgeos_agent").joinpath("samples").joinpath("people_detection.json").read_text()
)


@pytest.fixture
def sample() -> dict[str, Any]:
    """Return a fresh, mutable copy of the people-detection sample Skill config."""
    return copy.deepcopy(_SAMPLE)


class Cloud:
    """A daphne of the test's own on a fixed port, so the test can kill and restart the cloud."""

    def __init__(self, log: Path) -> None:
        self.port = free_port()
        self.log = watch(log)
        self.process: subprocess.Popen | None = None
        self.env: dict[str, str] = {}

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    def start(self) -> None:
        from django.conf import settings as django_settings

        env = service_env(django_settings.DATABASES["default"]["NAME"])
        with self.log.open("ab") as out:
            self.process = subprocess.Popen(
                [str(ROOT / "scripts" / "daphne"), "-b", "127.0.0.1", "-p", str(self.port)],
                cwd=ROOT,
                env={**env, "VIRTUAL_ENV": str(BIN.parent), **self.env},
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        wait_for_port(self.port, self.process)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()  # a crash, not a polite shutdown
            self.process.wait(10)


@pytest.fixture
def cloud(tmp_path, celery_worker_process) -> Cloud:
    # With a Celery worker: cloud-side launches really run (the process runtime, by default).
    server = Cloud(tmp_path / "daphne.log")
    server.start()
    yield server
    server.stop()


SKILL = "workers"


def skill_config(*, location: str = "robot", count: int = 2, cpu: float = 0.1) -> dict:
    """Return a Skill of `count` components that each sleep, runnable by the process runtime."""
    spec = {"command": ["sleep", "600"]}
    components = {
        f"worker-{n}": {
            "name": f"Worker {n}",
            "location": location,
            "ros": False,
            "resources": {"cpu": cpu, "ram": 16},
            "robot": spec,
            **({"cloud": spec} if location != "robot" else {}),
        }
        for n in range(count)
    }
    return parse_skill_config({"skill": "Workers", "skill_id": SKILL, "components": components}).model_dump(mode="json")


@sync_to_async
def make_robot(robot_id: str, *, config: dict | None = None, skill: dict | None = None) -> tuple[str, str]:
    """Create a robot (owner, optional config changes and Skill); return (robot token, API token)."""
    from django.contrib.auth import get_user_model

    owner = get_user_model().objects.create_user(f"owner-{robot_id}")
    robot, token = create_robot(robot_id, owner)
    if config:
        update_robot_config(robot.id, config)
    if skill:
        add_skill(robot, skill)
    return token, issue_api_token(owner)[0]


def agent_settings(cloud: Cloud, robot: str, token: str, data_dir: Path, **kw) -> AgentSettings:
    """Return settings for a simulated robot that samples fast, reports every sample and cleans up."""
    kw.setdefault("stop_components_on_exit", True)
    return AgentSettings(
        master=cloud.ws_url,
        robot=robot,
        token=token,
        data_dir=data_dir,
        simulate=True,
        simulated=SimulatedRobot(cpu=4, ram=4096, seed=1),
        sample_interval=kw.pop("sample_interval", 0.2),
        report_max_interval=0.0,
        reconnect_initial=0.2,
        reconnect_max=1.0,
        **kw,
    )


@contextlib.asynccontextmanager
async def running(controller: RobotController) -> AsyncIterator[RobotController]:
    """Run a controller for the body of a with block, then stop it."""
    task = asyncio.create_task(controller.run())
    try:
        yield controller
    finally:
        controller.stop()
        await asyncio.wait_for(task, 30)


def running_workers(controller: RobotController) -> dict[str, int]:
    """Return {component: pid} of the skill's components the runtime runs now."""
    state = controller.runtime.get_state()
    found = {}
    for entry in state.get("components", []):
        pid = entry.get("pid")
        if entry.get("skill") == SKILL and pid and psutil.pid_exists(pid):
            found[entry["component"]] = pid
    return found


@contextlib.asynccontextmanager
async def configured(controller: RobotController) -> AsyncIterator[RobotController]:
    """Run a controller for the body of a with block, from the moment it has its config from the cloud."""
    async with running(controller):
        await asyncio.wait_for(controller.config_from_cloud.wait(), 15)
        yield controller


@contextlib.asynccontextmanager
async def robot_agent(
    cloud: Cloud,
    robot_id: str,
    data_dir: Path,
    *,
    config: dict | None = None,
    skill: dict | None = None,
    plugins: Mapping[str, SkillPlugin] | None = None,
    **settings: Any,
) -> AsyncIterator[RobotController]:
    """Create a robot (with optional config changes and Skill) and run its agent, configured by the cloud."""
    token, _ = await make_robot(robot_id, config=config, skill=skill)
    controller = RobotController(agent_settings(cloud, robot_id, token, data_dir, **settings), plugins=plugins)
    async with configured(controller):
        yield controller


@pytest.fixture(scope="module")
def rosmaster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    """Start a ROS master of the test module's own."""
    with private_rosmaster(tmp_path_factory.mktemp("rosmaster")) as uri:
        yield uri


@pytest.fixture
def nodes(rosmaster: str, tmp_path: Path) -> Iterator[Nodes]:
    """Give a test rospy nodes on its module's ROS master, all killed when it ends."""
    runner = Nodes(rosmaster, tmp_path)
    try:
        yield runner
    finally:
        runner.kill_all()
