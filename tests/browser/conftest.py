"""Fixtures for the dashboard's browser tests: Debian's Chromium driven by Playwright against daphne.

Playwright's sync API runs an event loop in the test's thread while it is open, so the
browser lives only inside each test (its fixture is function-scoped and closes before
pytest-django flushes), and the ORM is allowed to run beside that loop while it does.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from django.contrib.auth import get_user_model

from bridgeos_agent.skillconfig import load_sample_skill_config
from robots.models import Robot
from robots.services import create_robot
from skills.services import add_skill

from .simrobot import start_simulated_robot, stop_simulated_robot

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_FLAGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-quic",
    "--no-first-run",
    "--disable-component-update",
    "--disable-sync",
]
ROOT = Path(__file__).resolve().parents[2]
ARTIFACTS = Path(os.environ.get("BRIDGEOS_TEST_ARTIFACTS", ROOT / ".data" / "test-artifacts")) / "browser"
PASSWORD_SUFFIX = "-pass-123"
SKILL = "people-detection"


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


def make_robot(owner: Any, robot_id: str, *, with_skill: bool = True) -> str:
    """Create a robot (with the sample people-detection Skill) and return its token."""
    robot, token = create_robot(robot_id, owner, name=f"Robot {robot_id}")
    if with_skill:
        add_skill(robot, load_sample_skill_config().model_dump(mode="json"))
    return token


def wait_until(check: Callable[[], bool], *, timeout: float = 15.0, what: str = "condition") -> None:
    """Poll the database (or anything) until a check holds."""
    deadline = time.monotonic() + timeout
    while not check():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        time.sleep(0.05)


class SimulatedRobots:
    """Simulated robots started for one test, each in its own process like an agent."""

    def __init__(self, ws_url: str, logs: Path) -> None:
        self.ws_url = ws_url
        self.logs = logs
        self.processes: dict[str, Any] = {}

    def start(self, robot_id: str, token: str, *, skills: tuple[str, ...] = (SKILL,), wait: bool = True) -> None:
        """Start a robot running these Skills; by default wait until the cloud has it connected."""
        log = self.logs / f"robot-{robot_id}.log"
        self.processes[robot_id] = start_simulated_robot(
            self.ws_url, robot_id, token, skills=skills, period=0.5, log=log
        )
        if wait:
            wait_until(
                lambda: Robot.objects.filter(id=robot_id, connected=True).exists(),
                timeout=20,
                what=f"robot {robot_id} to connect (its log: {log})",
            )

    def stop(self, robot_id: str) -> None:
        """Stop a robot's process: its socket closes."""
        stop_simulated_robot(self.processes.pop(robot_id))

    def stop_all(self) -> None:
        ids = list(self.processes)
        for robot_id in ids:
            self.stop(robot_id)
        wait_until(
            lambda: not Robot.objects.filter(id__in=ids, connected=True).exists(),
            what="simulated robots to disconnect",
        )


@pytest.fixture
def simulated_robots(daphne_server, transactional_db, tmp_path) -> Iterator[SimulatedRobots]:
    """Start simulated robots for a test and stop them after it."""
    robots = SimulatedRobots(daphne_server.ws_url, tmp_path)
    yield robots
    robots.stop_all()
