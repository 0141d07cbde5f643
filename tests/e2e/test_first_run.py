"""`make run` as a new user meets it: a clean data directory, default settings, the demo fleet, then Ctrl-C.

Every demo component must reach `running` (on the robot or in the cloud, as Swarm services here), no
log of the run may hold an ERROR line or a traceback, the dashboard's robot page must render in
Chromium without console errors, the terminal must stay quiet (a status line per part and the
login), and Ctrl-C must leave nothing behind: no process, Swarm service or network of the run.
"""

from __future__ import annotations

import os
import re
import shutil
import signal
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import httpx
import pytest

from tests.conftest import ROOT, free_port
from tests.logguard import is_bad

pytestmark = [pytest.mark.slow, pytest.mark.docker, pytest.mark.browser, pytest.mark.timeout(900)]

CHROMIUM = "/usr/bin/chromium"
START_S = 120  # until the terminal says the cloud runs
SETTLE_S = 420  # until every demo component has run
STOP_S = 120  # from Ctrl-C until every process of the run is gone


class Run:
    """`make run` in a session of its own, its terminal read line by line."""

    def __init__(self, data: Path, port: int, registry_port: int) -> None:
        env = {k: v for k, v in os.environ.items() if k not in ("DATABASE_URL", "PROMETHEUS_MULTIPROC_DIR")}
        env.update(
            BRIDGEOS_DATA_DIR=str(data),  # clean: the embedded SQLite database, new logs
            BRIDGEOS_PORT=str(port),
            BRIDGEOS_REGISTRY_PORT=str(registry_port),
            # A Redis database of its own, as `make run` takes database 0 on a machine of its own.
            REDIS_URL="redis://127.0.0.1:6379/13",
        )
        self.data = data
        self.process = subprocess.Popen(
            ["make", "--no-print-directory", "run"],
            cwd=ROOT,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,  # its own process group: Ctrl-C reaches it all, as in a terminal
        )
        self.lines: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self.seen: dict[int, tuple[str, str]] = {}  # pid -> (start time, command line) of every process

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            self.lines.append(line)

    @property
    def output(self) -> str:
        return "".join(self.lines)

    def wait_for_line(self, text: str, timeout: float) -> None:
        deadline = time.monotonic() + timeout
        while not any(text in line for line in self.lines):
            assert self.process.poll() is None, "make run ended early:\n" + self.output
            assert time.monotonic() < deadline, f"no {text!r} within {timeout} s:\n" + self.output
            time.sleep(0.2)

    def note_processes(self) -> None:
        """Remember every process descended from `make run` now (a component's too, in a session of its own)."""
        children: dict[int, list[int]] = {}
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit() and (stat := _stat(int(entry.name))) is not None:
                children.setdefault(stat[0], []).append(int(entry.name))
        todo = [self.process.pid]
        while todo:
            pid = todo.pop()
            stat = _stat(pid)
            if stat is not None and pid not in self.seen:
                self.seen[pid] = (stat[1], _cmdline(pid))
            todo += children.get(pid, [])

    def alive(self) -> list[str]:
        """Return the processes noted that still run (the same process: its start time unchanged)."""
        return [f"{pid} {cmd}" for pid, (start, cmd) in self.seen.items() if (s := _stat(pid)) and s[1] == start]

    def interrupt(self) -> None:
        os.killpg(self.process.pid, signal.SIGINT)

    def kill(self) -> None:
        for pid in list(self.seen):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass


def _stat(pid: int) -> tuple[int, str] | None:
    """Return a process's parent pid and start time, or None once it is gone (or a zombie)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except (FileNotFoundError, ProcessLookupError, IndexError):
        return None
    return (int(fields[1]), fields[19]) if fields[0] != "Z" else None


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")[:200]
    except OSError:
        return "?"


def docker_names(kind: str) -> set[str]:
    done = subprocess.run(["docker", kind, "ls", "--format", "{{.Name}}"], capture_output=True, text=True, check=True)
    return set(done.stdout.split())


def components(api: httpx.Client) -> dict[str, tuple[str, str]]:
    """Return every demo component's (status, reason), keyed robot/skill/component, through the Robot API."""
    found = {}
    for robot in api.get("/api/robot").raise_for_status().json():
        info = api.get(f"/api/robot/{robot['id']}/info").raise_for_status().json()
        for skill in info["skills"]:
            for component in skill["components"]:
                key = f"{robot['id']}/{skill['skill_id']}/{component['component_id']}"
                found[key] = (component["status"], component.get("message", ""))
    return found


def bad_lines(root: Path) -> list[str]:
    """Return the ERROR lines and tracebacks of every log under a directory, with where they are."""
    found = []
    for log in sorted(root.rglob("*.log")):
        for number, line in enumerate(log.read_text(errors="replace").splitlines(), 1):
            if is_bad(line):
                found.append(f"{log.relative_to(root)}:{number}: {line[:300]}")
    return found


def agent_lines(data: Path, components: dict[str, tuple[str, str]]) -> str:
    """Return what the robots' logs say of these components and of their resources, to tell why they never ran."""
    lines = []
    for key in components:
        robot, skill, component = key.split("/")
        log = data / "agents" / f"{robot}.log"
        text = log.read_text(errors="replace").splitlines() if log.exists() else []
        lines += [f"{robot}: {line}" for line in text if f"{skill}/{component}" in line or "short of" in line][-40:]
    return "\n".join(lines)


def render_robot_page(base_url: str, username: str, password: str, robot: str) -> list[str]:
    """Log in through the form, open a robot's page in Chromium; return the console's errors."""
    from playwright.sync_api import expect, sync_playwright

    console: list[str] = []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=CHROMIUM,
            args=["--no-sandbox", "--disable-gpu", "--disable-background-networking", "--disable-quic"],
        )
        try:
            page = browser.new_page()
            page.on("console", lambda m: console.append(f"{m.type}: {m.text}"))
            page.on("pageerror", lambda e: console.append(f"page error: {e}"))
            page.goto(f"{base_url}/accounts/login/")
            page.get_by_label("Username").fill(username)
            page.get_by_label("Password").fill(password)
            page.get_by_role("button", name="Log in").click()
            page.wait_for_url(f"{base_url}/")
            page.goto(f"{base_url}/robots/{robot}/")
            page.wait_for_selector('#live-status[data-state="live"]', timeout=15_000)
            rows = page.locator("tr[data-component]")
            expect(rows.first).to_be_visible(timeout=15_000)
            assert rows.count() >= 6  # the demo robot's Skills' components
            page.wait_for_timeout(3_000)  # live frames and charts arrive
        finally:
            browser.close()
    return [line for line in console if line.startswith(("error", "page error"))]


@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason="Debian's chromium is not installed")
def test_make_run_from_a_clean_data_directory_runs_every_demo_component_and_leaves_nothing(tmp_path):
    data = tmp_path / "data"
    port = free_port()
    services, networks = docker_names("service"), docker_names("network")
    registry_port = free_port()
    run = Run(data, port, registry_port)
    try:
        run.wait_for_line("Press Ctrl-C", START_S)
        login = re.search(r"Operator account created: (\S+) / (\S+)", run.output)
        assert login, run.output
        username, password = login.groups()
        base_url = f"http://127.0.0.1:{port}"
        token = httpx.get(f"{base_url}/api/auth", auth=(username, password)).raise_for_status().json()["token"]
        if shutil.which("docker-registry"):
            # The run's registry sends its clients to this cloud for tokens, and takes this cloud's.
            challenge = httpx.get(f"http://127.0.0.1:{registry_port}/v2/", timeout=10)
            assert challenge.status_code == 401
            assert f'realm="{base_url}/api/registry/token"' in challenge.headers["WWW-Authenticate"]
            granted = httpx.get(
                f"{base_url}/api/registry/token",
                params={"service": "bridgeos-registry", "scope": f"repository:{username}/x:pull"},
                auth=(username, password),
            ).raise_for_status()
            taken = httpx.get(
                f"http://127.0.0.1:{registry_port}/v2/", headers={"Authorization": f"Bearer {granted.json()['token']}"}
            )
            assert taken.status_code == 200, taken.text
        api = httpx.Client(base_url=base_url, headers={"Authorization": f"Token {token}"}, timeout=30)

        # Every component of every demo Skill runs, on the robot or in the cloud (they move meanwhile).
        ran: set[str] = set()
        latest: dict[str, tuple[str, str]] = {}
        deadline = time.monotonic() + SETTLE_S
        while True:
            run.note_processes()
            latest = components(api)
            ran |= {key for key, (status, _) in latest.items() if status == "running"}
            if len(latest) >= 20 and ran == set(latest):
                break
            assert run.process.poll() is None, "make run ended early:\n" + run.output
            if time.monotonic() > deadline:
                never = {key: latest[key] for key in sorted(set(latest) - ran)}
                raise AssertionError(f"never running within {SETTLE_S} s: {never}\n{agent_lines(data, never)}")
            time.sleep(2)
        failed = {key: state for key, state in latest.items() if state[0] == "failed"}
        assert failed == {}
        assert docker_names("service") - services, "no cloud copy ran as a Swarm service"

        assert render_robot_page(base_url, username, password, "demo-1") == []
        run.note_processes()
        api.close()
    finally:
        run.interrupt()
        try:
            run.process.wait(STOP_S)
        except subprocess.TimeoutExpired:
            run.kill()
            raise
    deadline = time.monotonic() + 30
    while run.alive() and time.monotonic() < deadline:
        time.sleep(0.5)
    assert run.alive() == [], "processes of the run outlived it"
    assert docker_names("service") - services == set(), "Swarm services of the run outlived it"
    assert docker_names("network") - networks == set(), "networks of the run outlived it"

    # The terminal: one status line per part and the login; the parts' output went to their files.
    output = run.output
    assert not re.search(r"warn|error|traceback|GET /|POST /", output, re.IGNORECASE), output
    statuses = [line.split(":")[0].strip() for line in output.splitlines() if line.startswith("  ") and ":" in line]
    for part in ("database", "runtime", "celery", "daphne", "registry", "demo", "metrics"):
        assert statuses.count(part) == 1, output
    assert "cloud copies run as swarm" in output
    for name in ("daphne.log", "celery.log", "demo_fleet.log"):
        assert str(data / "logs" / name) in output and (data / "logs" / name).stat().st_size > 0, name
    # And no log of the run, the cloud's or a robot's or a component's, holds an error.
    assert bad_lines(data / "logs") + bad_lines(data / "agents") == []


def test_a_bad_line_is_found_wherever_a_log_of_the_run_has_it(tmp_path: Path) -> None:
    (tmp_path / "agents" / "demo-1" / "runtime" / "logs").mkdir(parents=True)
    (tmp_path / "agents" / "demo-1.log").write_text("01:00:00 connecting\n01:00:01 ERROR cannot serve --rosbridge\n")
    (tmp_path / "agents" / "demo-1" / "runtime" / "logs" / "node.log").write_text(
        "ok\nTraceback (most recent call last):\n  File x\n"
    )
    (tmp_path / "agents" / "fine.log").write_text("01:00:00 WARNING slow link\nerrors: 0\n")
    found: list[Any] = bad_lines(tmp_path)
    assert sorted(found) == [
        "agents/demo-1.log:2: 01:00:01 ERROR cannot serve --rosbridge",
        "agents/demo-1/runtime/logs/node.log:2: Traceback (most recent call last):",
    ]
