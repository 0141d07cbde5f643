"""The robot-side fault scenarios' rig: a cloud of their own, real agents, a robot's own network namespace.

Nothing here sets Django up in the runner's process (other scenarios share it): robots and
Skills are made by `manage.py shell` in a child process, and figures are read with plain SQL,
from the agent's own Prometheus exporter and from the process table.

    BRIDGEOS_CHAOS_DATABASE_URL   default postgres://postgres@127.0.0.1:5432/bridgeos_chaos_robot
    BRIDGEOS_CHAOS_REDIS_URL      default redis://127.0.0.1:6379/12
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections import Counter
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import httpx
import psutil

from benchmarks._common import ROOT, CeleryWorker, ensure_postgres_database, free_port, log, migrate
from bridgeos_agent.runtime.cgroups import Cgroups
from tests.net.netns import Network, _in_namespace, run

VENV_BIN = Path(sys.executable).parent


def chaos_env(name: str, workdir: Path) -> dict[str, str]:
    """Return the environment of the scenario's cloud processes."""
    return {
        "DATABASE_URL": os.environ.get(
            "BRIDGEOS_CHAOS_DATABASE_URL", "postgres://postgres@127.0.0.1:5432/bridgeos_chaos_robot"
        ),
        "REDIS_URL": os.environ.get("BRIDGEOS_CHAOS_REDIS_URL", "redis://127.0.0.1:6379/12"),
        "BRIDGEOS_DATA_DIR": str(workdir / "cloud"),
        "BRIDGEOS_CLOUD_RUNTIME": "process",
        "BRIDGEOS_CLOUD_ID": f"chaos-{name}-{uuid.uuid4().hex[:6]}",
        "BRIDGEOS_CLOUD_ROS_MASTERS": "0",
        "BRIDGEOS_COMMAND_WAIT_S": "30",
        "CELERY_TASK_DEFAULT_QUEUE": f"chaos-{name}-{uuid.uuid4().hex[:8]}",
        "PYTHONUNBUFFERED": "1",
    }


def wait_until(check: Callable[[], Any], what: str, timeout: float, interval: float = 0.1) -> Any:
    """Poll until check() is truthy; raise saying what did not happen."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


class CloudServer:
    """A daphne of the scenario's own on a fixed address and port, so it can be killed and restarted."""

    def __init__(self, env: dict[str, str], log_path: Path, host: str = "127.0.0.1") -> None:
        self.env = env
        self.host = host
        self.port = free_port()
        self.log_path = log_path
        self.process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def start(self, timeout: float = 60.0) -> None:
        with self.log_path.open("ab") as out:
            self.process = subprocess.Popen(
                [str(ROOT / "scripts" / "daphne"), "-b", self.host, "-p", str(self.port)],
                cwd=ROOT,
                env={**os.environ, **self.env, "VIRTUAL_ENV": str(VENV_BIN.parent)},
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        deadline = time.monotonic() + timeout
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"daphne exited: {self.log_path.read_text(errors='replace')[-2000:]}")
            try:
                socket.create_connection((self.host, self.port), timeout=0.2).close()
                return
            except OSError:
                if time.monotonic() > deadline:
                    raise TimeoutError("daphne did not listen") from None
                time.sleep(0.05)

    def kill(self) -> None:
        """Kill daphne with SIGKILL, as a crash would."""
        if self.process is not None and self.process.poll() is None:
            self.process.kill()
            self.process.wait(10)


SETUP = """
import json, os
from django.contrib.auth import get_user_model
from bridgeos_agent.skillconfig import parse_skill_config
from robots.models import Robot
from robots.services import create_robot, issue_api_token, update_robot_config
from skills.services import add_skill
spec = json.loads(os.environ["CHAOS_SPEC"])
Robot.objects.filter(id=spec["robot"]).delete()
owner, _ = get_user_model().objects.get_or_create(username="chaos-" + spec["robot"])
robot, token = create_robot(spec["robot"], owner)
if spec.get("config"):
    update_robot_config(robot.id, spec["config"])
for skill in spec["skills"]:
    add_skill(robot, parse_skill_config(skill).model_dump(mode="json"))
print(json.dumps({"token": token, "api": issue_api_token(owner)[0]}))
"""


class Cloud:
    """The scenario's cloud: its database migrated, daphne, and a Celery worker when cloud copies must run."""

    def __init__(self, name: str, *, host: str = "127.0.0.1", celery: bool = False) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix=f"bridgeos-chaos-{name}-"))
        self.env = chaos_env(name, self.dir)
        if host != "127.0.0.1":
            self.env["ALLOWED_HOSTS"] = f"{host},127.0.0.1,localhost"
        ensure_postgres_database(self.env["DATABASE_URL"])
        started = time.monotonic()
        migrate(self.env)
        log(f"{name}: database migrated in {time.monotonic() - started:.1f} s")
        self.server = CloudServer(self.env, self.dir / "daphne.log", host)
        self.celery: CeleryWorker | None = None
        self._want_celery = celery

    def start(self) -> None:
        self.server.start()
        if self._want_celery:
            self.celery = CeleryWorker({**self.env}, self.env["CELERY_TASK_DEFAULT_QUEUE"], self.dir / "worker.log")

    def wait_celery(self, timeout: float = 60.0) -> None:
        """Wait until the worker answers a ping (asked by a child process: no Celery app in the runner's)."""
        if self.celery is None:
            return
        command = [str(VENV_BIN / "celery"), "-A", "bridgeos_cloud", "inspect", "ping", "-d", self.celery.name]
        env = {**os.environ, **self.env}

        def answers() -> bool:
            assert self.celery is not None
            if self.celery.process.poll() is not None:
                raise RuntimeError(f"the Celery worker exited: {tail(self.dir / 'worker.log')}")
            done = subprocess.run([*command, "-t", "1"], cwd=ROOT, env=env, capture_output=True, timeout=30)
            return done.returncode == 0

        wait_until(answers, "the Celery worker", timeout, interval=0.5)

    def stop(self) -> None:
        if self.celery is not None:
            self.celery.stop()
        self.server.kill()

    def add_robot(self, robot: str, *, config: dict | None = None, skills: list[dict] = ()) -> tuple[str, str]:
        """Create a robot (and its owner, config and Skills); return (robot token, API token)."""
        spec = json.dumps({"robot": robot, "config": config, "skills": list(skills)})
        done = subprocess.run(
            [sys.executable, str(ROOT / "manage.py"), "shell", "-c", SETUP],
            cwd=ROOT,
            env={**os.environ, **self.env, "CHAOS_SPEC": spec},
            capture_output=True,
            text=True,
            timeout=120,
        )
        if done.returncode != 0:
            raise RuntimeError(f"creating robot {robot} failed: {done.stderr[-2000:]}")
        answer = json.loads(done.stdout.strip().splitlines()[-1])
        return answer["token"], answer["api"]

    def api(self, api_token: str, method: str, path: str, **kw: Any) -> httpx.Response:
        with httpx.Client(base_url=self.server.url, headers={"Authorization": f"Token {api_token}"}) as client:
            return client.request(method, path, timeout=60, **kw)

    def sql(self, query: str, params: list[Any] | tuple[Any, ...] = ()) -> list[tuple]:
        import psycopg

        with psycopg.connect(self.env["DATABASE_URL"], autocommit=True) as conn:
            return conn.execute(query, params).fetchall()

    def metric_rows(self, robot: str) -> tuple[int, int]:
        """Return (rows, rows beyond the first of each identical point) stored for a robot."""
        rows = self.sql(
            "SELECT count(*), count(*) - count(DISTINCT (name, ts, skill, component))"
            " FROM monitoring_metric WHERE robot_id = %s",
            [robot],
        )
        return int(rows[0][0]), int(rows[0][1])

    def out_of_order(self, robot: str, name: str = "cpu") -> int:
        """Count points of one robot-level series stored after a later one (by arrival id)."""
        rows = self.sql(
            "SELECT count(*) FROM (SELECT ts, lag(ts) OVER (ORDER BY id) AS before FROM monitoring_metric"
            " WHERE robot_id = %s AND name = %s AND skill = '' AND component = '') s WHERE ts < before",
            [robot, name],
        )
        return int(rows[0][0])


class Agent:
    """The real agent (`bridgeos-agent run --simulate`), optionally inside a network namespace."""

    def __init__(
        self,
        robot: str,
        token: str,
        master: str,
        data_dir: Path,
        log_path: Path,
        *,
        namespace: str | None = None,
        sample_interval: float = 0.5,
        options: Sequence[str] = (),
    ) -> None:
        self.robot = robot
        self.namespace = namespace
        self.data_dir = data_dir
        self.log_path = log_path
        self.metrics_port = free_port()
        command = [
            str(VENV_BIN / "bridgeos-agent"),
            "run",
            "--master",
            master,
            "--robot",
            robot,
            "--token",
            token,
            "--simulate",
            "--runtime",
            "process",
            "--data-dir",
            str(data_dir),
            "--sample-interval",
            str(sample_interval),
            "--metrics",
            f"127.0.0.1:{self.metrics_port}",
            "--allow-insecure",
            "--stop-components-on-exit",
            *options,
        ]
        if namespace is not None:
            command = ["ip", "netns", "exec", namespace, *command]
        with log_path.open("ab") as out:
            self.process = subprocess.Popen(
                command, cwd=ROOT, env={**os.environ, "PYTHONUNBUFFERED": "1"}, stdout=out, stderr=subprocess.STDOUT
            )

    def alive(self) -> bool:
        return self.process.poll() is None

    def scrape(self) -> dict[str, float]:
        """Read the agent's exporter (from inside its namespace): {metric name: value summed over labels}."""

        def get() -> str:
            with httpx.Client(timeout=5) as client:
                return client.get(f"http://127.0.0.1:{self.metrics_port}/metrics").text

        text = _in_namespace(self.namespace, get) if self.namespace else get()
        values: dict[str, float] = Counter()
        for line in str(text).splitlines():
            match = re.match(r"^([a-zA-Z_:][\w:]*)(\{[^}]*\})? ([-+\deE.naif]+)$", line)
            if match:
                values[match.group(1)] += float(match.group(3))
        return dict(values)

    def try_scrape(self) -> dict[str, float] | None:
        try:
            return self.scrape()
        except (httpx.HTTPError, OSError):
            return None

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace")

    def stop(self, timeout: float = 30.0) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(10)


def settled_points(agent: Agent, cloud: Cloud, robot: str, timeout: float = 60.0) -> tuple[dict[str, float], int, int]:
    """Return (the agent's figures, rows stored, duplicate rows) at a moment nothing was in flight.

    Nothing is owed (outbox empty, no unstored frame unacked, disk writable) at one scrape, the
    rows are counted, and a second scrape shows no point was sent in between: then every point the
    agent counts as sent was either stored or counted as dropped, and no later one was counted.
    """
    deadline = time.monotonic() + timeout
    while True:
        first = agent.try_scrape() or {}
        if _idle(first):
            stored, duplicated = cloud.metric_rows(robot)
            second = agent.try_scrape() or {}
            sent = "bridgeos_agent_metric_points_sent_total"
            if _idle(second) and second.get(sent) == first.get(sent):
                return first, stored, duplicated
        if time.monotonic() > deadline:
            raise TimeoutError(f"the agent never settled (nothing owed, nothing sent between two reads): {first}")
        time.sleep(0.05)


def _idle(stats: dict[str, float]) -> bool:
    return (
        stats.get("bridgeos_agent_link_up") == 1
        and stats.get("bridgeos_agent_outbox_frames") == 0
        and stats.get("bridgeos_agent_unstored_frames_in_flight", 0) == 0
        and stats.get("bridgeos_agent_outbox_disk_full", 0) == 0
    )


def _component_processes(robot: str, skill: str) -> list[tuple[psutil.Process, str, str]]:
    found = []
    for proc in psutil.process_iter(["pid"]):
        try:
            if proc.status() == psutil.STATUS_ZOMBIE:
                continue
            env = proc.environ()
        except psutil.Error:
            continue
        if env.get("BRIDGEOS_ROBOT") == robot and env.get("BRIDGEOS_SKILL") == skill and "BRIDGEOS_COMPONENT" in env:
            found.append((proc, env["BRIDGEOS_COMPONENT"], env.get("BRIDGEOS_LOCATION", "?")))
    return found


def instances(robot: str, skill: str) -> Counter[tuple[str, str]]:
    """Count the running processes of a Skill's components, per (component, location), robot and cloud copies."""
    return Counter((component, location) for _, component, location in _component_processes(robot, skill))


def kill_instances(robot: str, skill: str) -> int:
    """Kill every process of a Skill's components (cloud copies outlive their worker by design)."""
    found = _component_processes(robot, skill)
    for proc, _, _ in found:
        with contextlib.suppress(psutil.Error):
            proc.kill()
    psutil.wait_procs([proc for proc, _, _ in found], timeout=5)
    # Their control groups too: no runtime saw them end.
    Cgroups(robot).sweep(min_age_s=0)
    return len(found)


class RobotLink:
    """A robot's network namespace joined to this machine by one veth pair it can cut and restore."""

    def __init__(self) -> None:
        self.net = Network()
        self.namespace = self.net.host("robot")
        subnet = _free_subnet()
        self.cloud_address, self.robot_address = f"10.254.{subnet}.1", f"10.254.{subnet}.2"
        self.outside, self.inside = f"bc{self.net.tag}o"[:15], f"bc{self.net.tag}i"[:15]
        run("ip", "link", "add", self.outside, "type", "veth", "peer", "name", self.inside, "netns", self.namespace)
        run("ip", "addr", "add", f"{self.cloud_address}/30", "dev", self.outside)
        run("ip", "link", "set", self.outside, "up")
        self.net.exec(self.namespace, "ip", "addr", "add", f"{self.robot_address}/30", "dev", self.inside)
        self.net.exec(self.namespace, "ip", "link", "set", self.inside, "up")

    def cut(self) -> None:
        """Take the robot's end of the link down: nothing passes, no socket is told."""
        self.net.exec(self.namespace, "ip", "link", "set", self.inside, "down")

    def restore(self) -> None:
        self.net.exec(self.namespace, "ip", "link", "set", self.inside, "up")

    def close(self) -> None:
        run("ip", "link", "del", self.outside, check=False)
        self.net.close()


def _free_subnet() -> int:
    """Pick a 10.254.N.0/30 no interface of this machine uses."""
    used = run("ip", "-4", "-o", "addr", "show").stdout
    for n in range(os.getpid() % 200 + 20, 255):
        if f"10.254.{n}." not in used:
            return n
    raise RuntimeError("no free 10.254.N.0/30 for the robot's link")


def tail(path: Path, chars: int = 1500) -> str:
    with contextlib.suppress(OSError):
        return path.read_text(errors="replace")[-chars:]
    return ""


__all__ = [
    "Agent",
    "Cloud",
    "CloudServer",
    "RobotLink",
    "instances",
    "kill_instances",
    "log",
    "settled_points",
    "tail",
    "wait_until",
]
