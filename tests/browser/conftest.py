"""Fixtures for the dashboard's browser tests: Debian's Chromium driven by Playwright against daphne.

Playwright's sync API runs an event loop in the test's thread while it is open, so the
browser lives only inside each test (its fixture is function-scoped and closes before
pytest-django flushes), and the ORM is allowed to run beside that loop while it does.

Robots are played by the real agent (`bridgeos-agent run --simulate`, started only by
`start_agent`) wherever it can do what the test needs; the simulator in simrobot.py plays
them only for what the agent does not do yet (offloading decisions).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
from django.contrib.auth import get_user_model

from benchmarks._fleetpage import CHROMIUM, CHROMIUM_FLAGS  # one set of Chromium flags for tests and benchmarks
from bridgeos_agent.skillconfig import load_sample_skill_config
from robots.models import Robot, default_robot_config
from robots.services import create_robot, issue_api_token
from skills.services import add_skill
from teams.services import personal_organization
from tests.agent.roshelpers import HOST_PYTHON, Nodes, private_rosmaster
from tests.conftest import BIN, wait_until
from tests.logguard import watch

from .simrobot import start_simulated_robot, stop_simulated_robot

ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = Path(os.environ.get("BRIDGEOS_TEST_ARTIFACTS", ROOT / ".data" / "test-artifacts")) / "browser"
PASSWORD_SUFFIX = "-pass-123"
# The sample Skill of the catalog tests and of simulated robots; its components need Docker images.
SKILL = "people-detection"
# The sample Skill the real agent runs with its process runtime: three shell loops (robot, either, either).
AGENT_SKILL = "demo-telemetry"
AGENT = BIN / "bridgeos-agent"
AGENT_STOP_S = 30.0


@dataclass
class Browser:
    """One fresh browser context and page, with what its console said."""

    page: Any
    base_url: str
    console: list[str] = field(default_factory=list)
    # HTTP statuses a test provokes on purpose; Chromium logs each failed response as a console error.
    expected_statuses: set[int] = field(default_factory=set)

    def expect_http_error(self, status: int) -> None:
        """Declare that the page will get this HTTP error status on purpose (e.g. 409 robot offline)."""
        self.expected_statuses.add(status)

    def console_errors(self) -> list[str]:
        """Return the console errors and page errors the test did not expect."""
        expected = tuple(f"status of {status} " for status in self.expected_statuses)
        return [
            line
            for line in self.console
            if line.startswith(("error", "page error"))
            and not (line.startswith("error: Failed to load resource") and any(s in line for s in expected))
        ]

    def login(self, username: str) -> None:
        """Log in through the login form, as an operator does."""
        page = self.page
        page.goto(f"{self.base_url}/accounts/login/")
        page.get_by_label("Username").fill(username)
        page.get_by_label("Password").fill(username + PASSWORD_SUFFIX)
        page.get_by_role("button", name="Log in").click()
        page.wait_for_url(f"{self.base_url}/")
        self.wait_live()

    def visit(self, path: str) -> Any:
        """Open a dashboard page by its path and return the page."""
        self.page.goto(self.base_url + path)
        return self.page

    def wait_live(self) -> None:
        """Wait until the page's /ws/client/ socket is authenticated."""
        self.page.wait_for_selector('#live-status[data-state="live"]', timeout=10_000)

    def screenshot(self, name: str, *, full_page: bool = True) -> Path:
        """Save a screenshot as a test artifact and return its path."""
        if self.page.locator("#live-status:not([hidden])").count():
            self.wait_live()
        if full_page:
            # A sticky header would be drawn where the page happened to be scrolled.
            self.page.evaluate("window.scrollTo(0, 0)")
        ARTIFACTS.mkdir(parents=True, exist_ok=True)
        path = ARTIFACTS / f"{name}.png"
        self.page.screenshot(path=str(path), full_page=full_page)
        return path


@pytest.fixture
def browser(daphne_server, transactional_db, monkeypatch) -> Iterator[Browser]:
    """Start Chromium with a fresh profile; fail the test if the page logged any console error."""
    if not Path(CHROMIUM).exists():
        pytest.skip(f"Debian's Chromium is not installed at {CHROMIUM}: run `scripts/services.sh chromium` as root")
    sync_api = pytest.importorskip(
        "playwright.sync_api", reason="playwright is not installed: pip install -e '.[test]'"
    )
    # The ORM refuses to run in a thread with a running event loop; Playwright's is only a driver.
    monkeypatch.setenv("DJANGO_ALLOW_ASYNC_UNSAFE", "true")
    sync_api.expect.set_options(timeout=10_000)
    with sync_api.sync_playwright() as playwright:
        # Playwright launches with a temporary profile directory (a fresh --user-data-dir) and removes it.
        chromium = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_FLAGS)
        context = chromium.new_context(viewport={"width": 1280, "height": 900}, locale="en-GB", timezone_id="UTC")
        context.set_default_timeout(15_000)
        page = context.new_page()
        session = Browser(page, daphne_server.url)
        page.on("console", lambda m: m.type in ("error", "warning") and session.console.append(f"{m.type}: {m.text}"))
        page.on("pageerror", lambda error: session.console.append(f"page error: {error}"))
        try:
            yield session
        finally:
            context.close()
            chromium.close()
    errors = session.console_errors()
    assert not errors, f"the page logged errors: {errors}"


def make_user(username: str, *, staff: bool = False) -> Any:
    """Create a user who logs in with the password `<username>-pass-123`."""
    return get_user_model().objects.create_user(username, password=username + PASSWORD_SUFFIX, is_staff=staff)


def make_robot(owner: Any, robot_id: str, *, sample: str | None = "people_detection") -> str:
    """Create a robot with one of the agent's sample Skills (or none) and return its token."""
    robot, token = create_robot(robot_id, owner, name=f"Robot {robot_id}")
    if sample:
        add_skill(robot, load_sample_skill_config(sample).model_dump(mode="json"))
    return token


def make_fleet(owner: Any, count: int, *, prefix: str = "fleet-", skip: tuple[str, ...] = ()) -> None:
    """Create robots `fleet-0000`… of the owner's in one bulk insert (thousands in a second), but those in `skip`."""
    organization, config = personal_organization(owner), default_robot_config()
    robots = []
    for i in range(count):
        robot = Robot(id=f"{prefix}{i:04d}", owner=owner, organization=organization, config=config)
        if robot.id not in skip:
            robot.issue_token()
            robots.append(robot)
    Robot.objects.bulk_create(robots, batch_size=1000)


def start_skill(base_url: str, owner: Any, robot_id: str, skill_id: str) -> None:
    """Start a robot's Skill through the Robot API, as an operator's script does, and check the robot accepted."""
    key, _ = issue_api_token(owner)
    response = httpx.post(
        f"{base_url}/api/robot/{robot_id}/skill/{skill_id}/start",
        params={"wait": 10},
        headers={"Authorization": f"Token {key}"},
        timeout=30,
    )
    assert response.status_code == 200 and response.json()["accepted"], response.text


def tail(log: Path, lines: int = 20) -> str:
    """Return the end of a robot's log, to say in a failure what the robot was doing."""
    try:
        return "\n".join(log.read_text(errors="replace").splitlines()[-lines:])
    except FileNotFoundError:
        return "(no log)"


# --------------------------------------------------------------------------- the real agent


def start_agent(master: str, robot_id: str, token: str, data_dir: Path, *, log: Path) -> subprocess.Popen:
    """Start the robot agent, simulated, with the process runtime: the one place tests start one."""
    command = [str(AGENT), "run", "--master", master, "--robot", robot_id, "--token", token]
    command += ["--runtime", "process", "--simulate", "--data-dir", str(data_dir), "--stop-components-on-exit"]
    with watch(log).open("ab") as out:
        return subprocess.Popen(
            command, env={**os.environ, "PYTHONUNBUFFERED": "1"}, stdout=out, stderr=subprocess.STDOUT
        )


def component_groups(data_dir: Path) -> dict[str, int]:
    """Return {"skill/component": process group} of the components the agent last recorded as running."""
    try:
        state = json.loads((data_dir / "state.json").read_text())
    except FileNotFoundError:
        return {}
    entries = (state.get("runtime") or {}).get("components", [])
    return {f"{entry['skill']}/{entry['component']}": entry["pid"] for entry in entries if entry.get("pid")}


def group_alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
    except ProcessLookupError:
        return False
    return True


def running_components(data_dir: Path) -> dict[str, int]:
    """Return the agent's components whose process group still runs."""
    return {key: pgid for key, pgid in component_groups(data_dir).items() if group_alive(pgid)}


def stop_agent(process: subprocess.Popen, data_dir: Path, log: Path) -> None:
    """Stop an agent as a service manager does (SIGTERM) and check that its components stopped with it."""
    process.terminate()
    try:
        code = process.wait(timeout=AGENT_STOP_S)
    except subprocess.TimeoutExpired:
        process.kill()
        code = process.wait()
    deadline = time.monotonic() + 5
    while running_components(data_dir) and time.monotonic() < deadline:
        time.sleep(0.05)
    left = running_components(data_dir)
    for pgid in left.values():
        # Each component leads a process group of its own: it would outlive the test.
        os.killpg(pgid, signal.SIGKILL)
    assert code == 0 and not left, (
        f"on SIGTERM the agent ended with {code} and left {sorted(left)} running:\n{tail(log)}"
    )


# --------------------------------------------------------------------------- robots started for a test


class RobotProcesses:
    """Robots started for one test, each in its own process with its own socket to the cloud."""

    kind = "robot"

    def __init__(self, ws_url: str, workdir: Path) -> None:
        self.ws_url = ws_url
        self.workdir = workdir
        self.processes: dict[str, subprocess.Popen] = {}

    def log(self, robot_id: str) -> Path:
        return self.workdir / f"{self.kind}-{robot_id}.log"

    def launch(self, robot_id: str, token: str) -> subprocess.Popen:
        raise NotImplementedError

    def terminate(self, robot_id: str, process: subprocess.Popen) -> None:
        raise NotImplementedError

    def start(self, robot_id: str, token: str, *, wait: bool = True) -> None:
        """Start a robot; by default wait until the cloud has it connected."""
        self.processes[robot_id] = self.launch(robot_id, token)
        if wait:
            self.wait_connected(robot_id)

    def wait_connected(self, robot_id: str) -> None:
        """Wait until the cloud has the robot connected; say what its log says if it does not."""
        try:
            wait_until(
                lambda: Robot.objects.filter(id=robot_id, connected=True).exists(),
                timeout=20,
                what=f"robot {robot_id} to connect",
            )
        except AssertionError as exc:
            raise AssertionError(f"{exc}; the end of {self.log(robot_id)}:\n{tail(self.log(robot_id))}") from None

    def stop(self, robot_id: str) -> None:
        """Stop a robot's process: its socket closes and the cloud marks it offline."""
        self.terminate(robot_id, self.processes.pop(robot_id))

    def stop_all(self) -> None:
        """Stop every robot still running, all of them even if one does not stop cleanly."""
        ids = list(self.processes)
        failures = []
        for robot_id in ids:
            try:
                self.stop(robot_id)
            except AssertionError as exc:
                failures.append(f"{robot_id}: {exc}")
        wait_until(
            lambda: not Robot.objects.filter(id__in=ids, connected=True).exists(),
            what=f"{self.kind}s to disconnect",
        )
        assert not failures, "\n".join(failures)


class Agents(RobotProcesses):
    """Real robot agents, simulated robots with the process runtime, each with a data directory of its own."""

    kind = "agent"

    def data_dir(self, robot_id: str) -> Path:
        return self.workdir / f"agent-{robot_id}"

    def running(self, robot_id: str) -> set[str]:
        """Return the "skill/component"s the robot's agent runs as processes now."""
        return set(running_components(self.data_dir(robot_id)))

    def launch(self, robot_id: str, token: str) -> subprocess.Popen:
        return start_agent(self.ws_url, robot_id, token, self.data_dir(robot_id), log=self.log(robot_id))

    def terminate(self, robot_id: str, process: subprocess.Popen) -> None:
        stop_agent(process, self.data_dir(robot_id), self.log(robot_id))


class SimulatedRobots(RobotProcesses):
    """Simulated robots (simrobot.py) running the people-detection Skill and inventing offloading decisions."""

    kind = "simulated-robot"

    def launch(self, robot_id: str, token: str) -> subprocess.Popen:
        return start_simulated_robot(self.ws_url, robot_id, token, skills=(SKILL,), period=0.5, log=self.log(robot_id))

    def terminate(self, robot_id: str, process: subprocess.Popen) -> None:
        stop_simulated_robot(process)


@pytest.fixture
def agents(daphne_server, celery_worker_process, transactional_db, tmp_path) -> Iterator[Agents]:
    """Start real robot agents for a test and stop them, and their components, after it."""
    robots = Agents(daphne_server.ws_url, tmp_path)
    yield robots
    robots.stop_all()


@pytest.fixture
def simulated_robots(daphne_server, transactional_db, tmp_path) -> Iterator[SimulatedRobots]:
    """Start simulated robots for a test and stop them after it."""
    robots = SimulatedRobots(daphne_server.ws_url, tmp_path)
    yield robots
    robots.stop_all()


# --------------------------------------------------------------------------- a ROS 1 graph


@pytest.fixture
def ros_graph(tmp_path, monkeypatch) -> Iterator[Nodes]:
    """Run a private rosmaster with a rospy talker on /chatter at 20 Hz; agents started next use it."""
    if not (Path(HOST_PYTHON).exists() and Path("/usr/bin/rosmaster").exists()):
        pytest.skip("Debian's ROS 1 (rospy, rosmaster) is not installed")
    with private_rosmaster(tmp_path) as master:
        nodes = Nodes(master, tmp_path)
        nodes.run("talker", "talker", "--topic", "/chatter", "--rate", "20", "--tag", "robot")
        monkeypatch.setenv("ROS_MASTER_URI", master)  # the agent started next finds this master
        try:
            yield nodes
        finally:
            nodes.kill_all()
