"""A private cloud to break: its environment and database, daphne, a Celery worker and beat, robots in it.

Every part runs as a process of its own, in a session of its own, so a scenario can `kill -9` it
and start it again: daphne on a fixed port (a restarted one is found at the same address), the
worker and beat logging every task they run. Nothing here sets Django up in the runner's process
(other scenarios share it) but `shared_cloud_env`: robots are made by the rig's own command in a
child process (`python -m benchmarks.chaos.rig`), figures are read with plain SQL.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import tempfile
import time
import uuid
from pathlib import Path
from typing import Any

import httpx
import psycopg

from benchmarks._common import ROOT, ensure_postgres_database, free_port, log, migrate, setup_django
from benchmarks.chaos.rig.base import (
    BIN,
    PYTHON,
    database_url,
    kill_group,
    listening,
    redis_url,
    scratch_dir,
    wait_until,
)


def private_env(database: str, redis: str, data_dir: Path, queue: str, **extra: str) -> dict[str, str]:
    """Return the environment of a private cloud: its stores, its data dir and a Celery queue of its own."""
    return {
        "DATABASE_URL": database,
        "REDIS_URL": redis,
        "BRIDGEOS_DATA_DIR": str(data_dir),
        "CELERY_TASK_DEFAULT_QUEUE": queue,
        "BRIDGEOS_CLOUD_RUNTIME": "process",
        "PYTHONUNBUFFERED": "1",
        **extra,
    }


def prepare_database(env: dict[str, str]) -> None:
    """Create the cloud's database if missing and migrate it."""
    ensure_postgres_database(env["DATABASE_URL"])
    migrate(env)


class CloudServer:
    """A daphne of the scenario's own on a fixed address and port, so a restarted one is found at the same place."""

    def __init__(self, env: dict[str, str], log_path: Path, *, host: str = "127.0.0.1") -> None:
        # The environment is read at each start: a caller may still add to it before then.
        self.env = env
        self.host = host
        self.port = free_port()
        self.log_path = log_path
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def start(self, timeout: float = 60.0) -> float:
        """Start daphne and return the wall time it accepted connections."""
        with self.log_path.open("ab") as out:
            self.process = subprocess.Popen(
                [str(ROOT / "scripts" / "daphne"), "-b", self.host, "-p", str(self.port)],
                cwd=ROOT,
                env={**os.environ, **self.env, "VIRTUAL_ENV": str(BIN.parent), "PYTHONUNBUFFERED": "1"},
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        process = self.process

        def up() -> bool:
            if process.poll() is not None:
                raise RuntimeError(f"daphne exited with {process.returncode}:\n{self.log_tail()}")
            return listening(self.host, self.port)

        wait_until(up, f"daphne listening on {self.port}", timeout, interval=0.02)
        return time.time()

    def kill(self) -> None:
        """kill -9 daphne, as a crash would."""
        if self.process is not None:
            kill_group(self.process)

    def stop(self) -> None:
        """Stop daphne politely (TERM), then for good."""
        if self.process is not None and self.process.poll() is None:
            kill_group(self.process, signal.SIGTERM)
            kill_group(self.process)

    def log_tail(self, chars: int = 3000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-chars:]
        except OSError:
            return ""


class Worker:
    """A Celery worker on the cloud's queue, logging every task it runs, in a session of its own."""

    def __init__(self, env: dict[str, str], log_path: Path, *, concurrency: int = 1) -> None:
        self.env = env
        self.log_path = log_path
        self.concurrency = concurrency
        self.starts = 0
        # Where this start's lines begin in the log every start appends to.
        self.log_offset = 0
        self.process: subprocess.Popen[bytes] | None = None

    def start(self, *, wait: bool = True) -> None:
        """Start the worker; with ``wait``, return once it consumes its queue."""
        self.starts += 1
        queue = self.env["CELERY_TASK_DEFAULT_QUEUE"]
        command = [str(BIN / "celery"), "-A", "bridgeos_cloud", "worker", "-P", "prefork", "-c", str(self.concurrency)]
        command += ["-l", "info", "-n", f"{queue}-{self.starts}@localhost", "-Q", queue, "--without-gossip"]
        command += ["--without-mingle", "--without-heartbeat"]
        self.log_offset = self.log_path.stat().st_size if self.log_path.exists() else 0
        with self.log_path.open("ab") as out:
            self.process = subprocess.Popen(
                command,
                cwd=ROOT,
                env={**os.environ, **self.env},
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        if wait:
            self.wait_ready()

    def log_text(self) -> str:
        try:
            return self.log_path.read_text(errors="replace")
        except OSError:
            return ""

    def wait_ready(self, timeout: float = 60.0) -> None:
        """Return once the worker consumes its queue (read from its log: no Celery app in the runner's process)."""
        wait_until(lambda: "ready." in self.log_text()[self.log_offset :] or self._died(), "the Celery worker", timeout)

    def _died(self) -> bool:
        if self.process is not None and self.process.poll() is not None:
            raise RuntimeError(f"the Celery worker exited:\n{self.log_text()[-3000:]}")
        return False

    def kill(self) -> None:
        """kill -9 the worker and its pool."""
        if self.process is not None:
            kill_group(self.process)

    def stop(self) -> None:
        """Warm shutdown (TERM to the main process only, so the pool finishes and reports), then for good."""
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.process.wait(20)
            kill_group(self.process)

    def succeeded(self, task: str) -> int:
        """Count how often a task succeeded, over every start of this worker."""
        lines = self.log_text().splitlines()
        return sum(1 for line in lines if f"Task {task}[" in line and " succeeded in " in line)


class Beat:
    """Celery beat with its schedule file in the scenario's directory, in a session of its own."""

    def __init__(self, env: dict[str, str], log_dir: Path) -> None:
        self.env = env
        self.log_dir = log_dir
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        command = [str(BIN / "celery"), "-A", "bridgeos_cloud", "beat", "-l", "info"]
        command += ["-s", str(self.log_dir / "beat-schedule"), "--pidfile", str(self.log_dir / "beat.pid")]
        with (self.log_dir / "beat.log").open("ab") as out:
            self.process = subprocess.Popen(
                command,
                cwd=ROOT,
                env={**os.environ, **self.env},
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def kill(self) -> None:
        if self.process is not None:
            kill_group(self.process)
        # A beat killed with -9 leaves its pid file, and the next one refuses to start beside it.
        (self.log_dir / "beat.pid").unlink(missing_ok=True)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            kill_group(self.process, signal.SIGTERM)
            kill_group(self.process)
        (self.log_dir / "beat.pid").unlink(missing_ok=True)


def _rig_command(env: dict[str, str], *args: str, stdin: str | None = None) -> str:
    """Run the rig's own command against a cloud's database; return the last line it printed."""
    done = subprocess.run(
        [PYTHON, "-m", "benchmarks.chaos.rig", *args],
        cwd=ROOT,
        env={**os.environ, **env},
        input=stdin,
        capture_output=True,
        text=True,
        timeout=120,
    )
    if done.returncode != 0:
        raise RuntimeError(f"rig {args[0]} failed: {done.stderr[-2000:]}")
    return done.stdout.strip().splitlines()[-1]


def create_robots(env: dict[str, str], prefix: str, count: int) -> list[tuple[str, str]]:
    """Create ``count`` fresh robots ``PREFIX-0000``..., each with its token; return (id, token) pairs."""
    pairs = json.loads(_rig_command(env, "robots", "--prefix", prefix, "--count", str(count)))
    return [(robot, token) for robot, token in pairs]


def api_token(env: dict[str, str]) -> str:
    """Issue a REST API token for the owner of the robots create_robots makes."""
    return _rig_command(env, "api-token")


class Cloud:
    """A whole private cloud: its env, its database migrated, daphne, and a Celery worker to start with it or apart.

    ``database`` and ``redis`` name stores of the scenario's own (default: the suite's); ``extra``
    adds to the cloud's environment.
    """

    def __init__(
        self,
        name: str,
        *,
        host: str = "127.0.0.1",
        celery: bool = False,
        concurrency: int = 2,
        database: str | None = None,
        redis: str | None = None,
        **extra: str,
    ) -> None:
        self.dir = scratch_dir(name)
        self.env = private_env(
            database or database_url(),
            redis or redis_url(),
            self.dir / "cloud",
            f"chaos-{name}-{uuid.uuid4().hex[:8]}",
            BRIDGEOS_CLOUD_ID=f"chaos-{name}-{uuid.uuid4().hex[:6]}",
            BRIDGEOS_CLOUD_ROS_MASTERS="0",
            BRIDGEOS_COMMAND_WAIT_S="30",
            **extra,
        )
        if host != "127.0.0.1":
            self.env["ALLOWED_HOSTS"] = f"{host},127.0.0.1,localhost"
        started = time.monotonic()
        prepare_database(self.env)
        log(f"{name}: database migrated in {time.monotonic() - started:.1f} s")
        self.server = CloudServer(self.env, self.dir / "daphne.log", host=host)
        self.worker = Worker(self.env, self.dir / "worker.log", concurrency=concurrency)
        self.celery = celery

    def start(self) -> None:
        """Start daphne, and the worker if the cloud runs one from the start (wait for it with wait_celery)."""
        self.server.start()
        if self.celery:
            self.worker.start(wait=False)

    def wait_celery(self, timeout: float = 60.0) -> None:
        """Wait until the worker consumes its queue (if the cloud has one)."""
        if self.celery:
            self.worker.wait_ready(timeout)

    def stop(self) -> None:
        self.worker.stop()
        self.server.kill()

    def add_robot(self, robot: str, *, config: dict | None = None, skills: list[dict] = ()) -> tuple[str, str]:
        """Create a robot (and its owner, config and Skills); return (robot token, API token)."""
        spec = json.dumps({"robot": robot, "config": config, "skills": list(skills)})
        answer = json.loads(_rig_command(self.env, "robot", stdin=spec))
        return answer["token"], answer["api"]

    def api(self, api_token: str, method: str, path: str, **kw: Any) -> httpx.Response:
        with httpx.Client(base_url=self.server.url, headers={"Authorization": f"Token {api_token}"}) as client:
            return client.request(method, path, timeout=60, **kw)

    def sql(self, query: str, params: list[Any] | tuple[Any, ...] = ()) -> list[tuple]:
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


def shared_cloud_env() -> dict[str, str]:
    """Return the environment of a cloud this process also serves, setting Django up here if it is not yet.

    The hostile and load scenarios read and write the cloud's tables from the runner's own process.
    """
    from django.apps import apps

    if apps.ready:
        # Inside the test suite (or after another scenario): serve the database this process already uses.
        from django.conf import settings

        db = settings.DATABASES["default"]
        url = f"postgres://{db['USER']}@{db['HOST'] or '127.0.0.1'}:{db['PORT'] or 5432}/{db['NAME']}"
        env = {"DATABASE_URL": url}
        for key in ("REDIS_URL", "BRIDGEOS_DATA_DIR"):
            if os.environ.get(key):
                env[key] = os.environ[key]
        env.setdefault("BRIDGEOS_DATA_DIR", tempfile.mkdtemp(prefix="bridgeos-chaos-"))
        return env
    env = {
        "DATABASE_URL": database_url(),
        "REDIS_URL": redis_url(),
        "BRIDGEOS_DATA_DIR": tempfile.mkdtemp(prefix="bridgeos-chaos-"),
    }
    prepare_database(env)
    setup_django(env)
    return env


def start_daphne(env: dict[str, str], name: str, extra: dict[str, str] | None = None) -> CloudServer:
    """Start a daphne of the scenario's own on the cloud of ``env`` and wait until it listens."""
    server = CloudServer({**env, **(extra or {})}, Path(env["BRIDGEOS_DATA_DIR"]) / f"{name}-daphne.log")
    server.start()
    return server
