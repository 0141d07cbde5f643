"""The fault suite's rig: private clouds, stores and fleets of real agents to break, and what they stored.

Every part runs as a process of its own so a scenario can `kill -9` it: daphne on a fixed port
(restarted on the same one), a Celery worker and beat, a private redis-server and a private
PostgreSQL cluster (initdb + pg_ctl in a temp dir), and a fleet process hosting several real
Robot Controllers (`bridgeos-agent run --simulate`, built from the agent's own argument parser)
that reports per robot what it sent, whether it is connected and what it still owes.

    python -m benchmarks.chaos._rig robots --prefix P --count N   # (run by create_robots) print ids and tokens
    python -m benchmarks.chaos._rig fleet SPEC.json               # (run by Fleet) host the agents of a spec
    python -m benchmarks.chaos._rig api-token                     # (run by api_token) a key for the robots' owner
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import psycopg

from benchmarks._common import ROOT, ensure_postgres_database, free_port, migrate

__all__ = [
    "AgentProcess",
    "Beat",
    "Cloud",
    "Fleet",
    "PrivatePostgres",
    "PrivateRedis",
    "StoredPoints",
    "Worker",
    "api_token",
    "cloud_env",
    "count_stored",
    "create_robots",
    "default_database_url",
    "default_redis_url",
    "eventually",
    "kill_group",
    "prepare_database",
    "scratch_dir",
]

PYTHON = sys.executable
BIN = Path(sys.executable).parent
PG_BIN = Path(os.environ.get("BRIDGEOS_PG_BIN", "/usr/lib/postgresql/15/bin"))
OWNER = "chaos-owner"


def default_database_url() -> str:
    """The PostgreSQL database the suite's clouds use: CHAOS_DATABASE_URL, else next to the test or dev one."""
    explicit = os.environ.get("CHAOS_DATABASE_URL")
    if explicit:
        return explicit
    base = os.environ.get("TEST_DATABASE_URL") or os.environ.get("DATABASE_URL") or ""
    if base.startswith("postgres"):
        # A database of its own beside the one named, so a test run's own database stays untouched.
        return base.rsplit("/", 1)[0] + "/" + base.rsplit("/", 1)[1].split("?")[0] + "_chaos"
    return "postgres://postgres@127.0.0.1:5432/bridgeos_chaos"


def default_redis_url() -> str:
    """The Redis the suite's clouds use when a scenario does not break Redis itself."""
    return (
        os.environ.get("CHAOS_REDIS_URL")
        or os.environ.get("TEST_REDIS_URL")
        or os.environ.get("REDIS_URL")
        or "redis://127.0.0.1:6379/13"
    )


def scratch_dir(name: str) -> Path:
    """Make a fresh temporary directory for one scenario's files."""
    return Path(tempfile.mkdtemp(prefix=f"chaos-{name}-"))


def eventually(check: Callable[[], Any], *, timeout: float, every: float = 0.05, what: str = "condition") -> Any:
    """Poll ``check`` until it returns something truthy; raise TimeoutError naming ``what``."""
    deadline = time.monotonic() + timeout
    while True:
        got = check()
        if got:
            return got
        if time.monotonic() > deadline:
            raise TimeoutError(f"{what}: not within {timeout:.0f} s")
        time.sleep(every)


def kill_group(process: subprocess.Popen[bytes], sig: int = signal.SIGKILL) -> None:
    """Send a signal to a process started in a session of its own, and to everything it started."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, sig)
    with contextlib.suppress(subprocess.TimeoutExpired):
        process.wait(30)


def _listening(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
    except OSError:
        return False
    return True


def cloud_env(database_url: str, redis_url: str, data_dir: Path, queue: str, **extra: str) -> dict[str, str]:
    """The environment of a private cloud: its stores, its data dir and a Celery queue of its own."""
    return {
        "DATABASE_URL": database_url,
        "REDIS_URL": redis_url,
        "BRIDGEOS_DATA_DIR": str(data_dir),
        "CELERY_TASK_DEFAULT_QUEUE": queue,
        "BRIDGEOS_CLOUD_RUNTIME": "process",
        "PYTHONUNBUFFERED": "1",
        **extra,
    }


def prepare_database(database_url: str, env: dict[str, str]) -> None:
    """Create the cloud's database if missing and migrate it."""
    ensure_postgres_database(database_url)
    migrate({**env, "DATABASE_URL": database_url})


def create_robots(env: dict[str, str], prefix: str, count: int) -> list[tuple[str, str]]:
    """Create ``count`` fresh robots ``PREFIX-0000``..., each with its token; return (id, token) pairs."""
    out = subprocess.run(
        [PYTHON, "-m", "benchmarks.chaos._rig", "robots", "--prefix", prefix, "--count", str(count)],
        cwd=ROOT,
        env={**os.environ, **env},
        check=True,
        capture_output=True,
        text=True,
    )
    return [tuple(pair) for pair in json.loads(out.stdout.strip().splitlines()[-1])]  # type: ignore[misc]


def _create_robots_here(prefix: str, count: int) -> list[tuple[str, str]]:
    """Create the robots through the cloud's own service (run inside the `robots` subcommand)."""
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "bridgeos_cloud.settings")
    import django

    django.setup()
    from django.contrib.auth import get_user_model

    from robots.models import Robot
    from robots.services import create_robot

    Robot.objects.filter(id__startswith=f"{prefix}-").delete()
    owner, _ = get_user_model().objects.get_or_create(username=OWNER)
    pairs = []
    for i in range(count):
        robot, token = create_robot(f"{prefix}-{i:04d}", owner)
        pairs.append((robot.id, token))
    return pairs


def api_token(env: dict[str, str]) -> str:
    """Issue a REST API token for the owner of the robots create_robots makes."""
    out = subprocess.run(
        [PYTHON, "-m", "benchmarks.chaos._rig", "api-token"],
        cwd=ROOT,
        env={**os.environ, **env},
        check=True,
        capture_output=True,
        text=True,
    )
    return out.stdout.strip().splitlines()[-1]


def _api_token_here() -> str:
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "bridgeos_cloud.settings")
    import django

    django.setup()
    from django.contrib.auth import get_user_model

    from robots.services import issue_api_token

    owner, _ = get_user_model().objects.get_or_create(username=OWNER)
    return issue_api_token(owner)[0]


@dataclass
class StoredPoints:
    """What PostgreSQL holds for some robots: every row, and the distinct points among them."""

    rows: int
    distinct: int

    @property
    def duplicated(self) -> int:
        return self.rows - self.distinct


def count_stored(database_url: str, robots: list[str]) -> StoredPoints:
    """Count the metric rows of some robots and the distinct points among them."""
    with psycopg.connect(database_url, autocommit=True, connect_timeout=10) as conn:
        rows, distinct = conn.execute(
            "SELECT count(*), count(DISTINCT (robot_id, skill, component, name, ts)) "
            "FROM monitoring_metric WHERE robot_id = ANY(%s)",
            [robots],
        ).fetchone()  # type: ignore[misc]
    return StoredPoints(rows, distinct)


# --------------------------------------------------------------------------- cloud processes


class Cloud:
    """A daphne of the scenario's own on a fixed port, so a restarted one is found at the same address."""

    def __init__(self, env: dict[str, str], log_dir: Path, *, port: int | None = None) -> None:
        self.env = env
        self.port = port or free_port()
        self.log_dir = log_dir
        self.starts = 0
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    def start(self, timeout: float = 60.0) -> float:
        """Start daphne and return the wall time it accepted connections."""
        self.starts += 1
        venv = Path(sys.executable).parent.parent
        with (self.log_dir / f"daphne-{self.starts}.log").open("wb") as out:
            self.process = subprocess.Popen(
                [str(ROOT / "scripts" / "daphne"), "-b", "127.0.0.1", "-p", str(self.port)],
                cwd=ROOT,
                env={**os.environ, **self.env, "VIRTUAL_ENV": str(venv)},
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        process = self.process

        def up() -> bool:
            if process.poll() is not None:
                raise RuntimeError(f"daphne exited with {process.returncode}:\n{self.log_tail()}")
            return _listening(self.port)

        eventually(up, timeout=timeout, every=0.02, what=f"daphne listening on {self.port}")
        return time.time()

    def kill(self) -> None:
        """kill -9 daphne."""
        if self.process is not None:
            kill_group(self.process)

    def stop(self) -> None:
        """Stop daphne politely (TERM), then for good."""
        if self.process is not None and self.process.poll() is None:
            kill_group(self.process, signal.SIGTERM)
            kill_group(self.process)

    def log_tail(self, chars: int = 3000) -> str:
        path = self.log_dir / f"daphne-{self.starts}.log"
        return path.read_text(errors="replace")[-chars:] if path.exists() else ""


class Worker:
    """A Celery worker on the scenario's queue, logging every task it runs, in a session of its own."""

    def __init__(self, env: dict[str, str], log_dir: Path, *, concurrency: int = 1) -> None:
        self.env = env
        self.log_dir = log_dir
        self.concurrency = concurrency
        self.starts = 0
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def log_path(self) -> Path:
        return self.log_dir / f"worker-{self.starts}.log"

    def start(self, *, wait: bool = True) -> None:
        """Start the worker; with ``wait``, return once it consumes its queue."""
        self.starts += 1
        queue = self.env["CELERY_TASK_DEFAULT_QUEUE"]
        command = [str(BIN / "celery"), "-A", "bridgeos_cloud", "worker", "-P", "prefork", "-c", str(self.concurrency)]
        command += ["-l", "info", "-n", f"{queue}-{self.starts}@localhost", "-Q", queue, "--without-gossip"]
        command += ["--without-mingle", "--without-heartbeat"]
        with self.log_path.open("wb") as out:
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

    def wait_ready(self) -> None:
        """Return once the worker consumes its queue."""
        eventually(
            lambda: "ready." in self.log_path.read_text(errors="replace") or self._died(),
            timeout=60,
            what="the Celery worker ready",
        )

    def _died(self) -> bool:
        if self.process is not None and self.process.poll() is not None:
            raise RuntimeError(f"the Celery worker exited:\n{self.log_path.read_text(errors='replace')[-3000:]}")
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
        """Count how often a task succeeded in every log of this worker."""
        logs = [self.log_dir / f"worker-{n}.log" for n in range(1, self.starts + 1)]
        return sum(_succeeded(path, task) for path in logs if path.exists())


def _succeeded(path: Path, task: str) -> int:
    lines = path.read_text(errors="replace").splitlines()
    return sum(1 for line in lines if f"Task {task}[" in line and " succeeded in " in line)


class Beat:
    """Celery beat with its schedule file in the scenario's directory, in a session of its own."""

    def __init__(self, env: dict[str, str], log_dir: Path) -> None:
        self.env = env
        self.log_dir = log_dir
        self.starts = 0
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.starts += 1
        command = [str(BIN / "celery"), "-A", "bridgeos_cloud", "beat", "-l", "info"]
        command += ["-s", str(self.log_dir / "beat-schedule"), "--pidfile", str(self.log_dir / "beat.pid")]
        with (self.log_dir / f"beat-{self.starts}.log").open("wb") as out:
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


# --------------------------------------------------------------------------- private stores


class PrivateRedis:
    """A redis-server of the scenario's own (own port, own dir, no persistence): free to restart."""

    def __init__(self, workdir: Path) -> None:
        self.port = free_port()
        self.workdir = workdir
        self.process: subprocess.Popen[bytes] | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        command = ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--dir", str(self.workdir)]
        command += ["--save", "", "--appendonly", "no", "--logfile", str(self.workdir / "redis.log")]
        self.process = subprocess.Popen(command, cwd=self.workdir, start_new_session=True)
        eventually(lambda: _listening(self.port), timeout=10, what=f"redis-server on {self.port}")

    def kill(self) -> None:
        if self.process is not None:
            kill_group(self.process)

    stop = kill


class PrivatePostgres:
    """A PostgreSQL cluster of the scenario's own (initdb in a temp dir, own port): free to restart."""

    def __init__(self, workdir: Path) -> None:
        self.port = free_port()
        self.data = workdir / "pgdata"
        self.logfile = workdir / "postgres.log"
        self.socket_dir = workdir

    @property
    def url(self) -> str:
        return f"postgres://postgres@127.0.0.1:{self.port}/bridgeos"

    def _as_postgres(self, command: list[str]) -> list[str]:
        # initdb and postgres refuse to run as root: run them as the postgres user then.
        if os.geteuid() == 0:
            return ["runuser", "-u", "postgres", "--", *command]
        return command

    def init(self) -> None:
        self.data.parent.mkdir(parents=True, exist_ok=True)
        if os.geteuid() == 0:
            shutil.chown(self.data.parent, "postgres")
        subprocess.run(
            self._as_postgres([str(PG_BIN / "initdb"), "-D", str(self.data), "-U", "postgres", "-A", "trust", "-N"]),
            check=True,
            capture_output=True,
        )
        with (self.data / "postgresql.conf").open("a") as conf:
            conf.write(
                f"port = {self.port}\nlisten_addresses = '127.0.0.1'\nunix_socket_directories = '{self.socket_dir}'\n"
            )
            conf.write("max_connections = 200\n")

    def start(self) -> None:
        subprocess.run(
            self._as_postgres([str(PG_BIN / "pg_ctl"), "-D", str(self.data), "-l", str(self.logfile), "-w", "start"]),
            check=True,
            capture_output=True,
        )

    def stop(self, mode: str = "fast") -> None:
        """Stop the cluster; mode ``immediate`` drops every connection mid-statement, like a crash."""
        subprocess.run(
            self._as_postgres([str(PG_BIN / "pg_ctl"), "-D", str(self.data), "-m", mode, "-w", "stop"]),
            check=False,
            capture_output=True,
        )


# --------------------------------------------------------------------------- real agents


class AgentProcess:
    """`bridgeos-agent run` itself, in its own process: the one to `kill -9` (its components live on)."""

    def __init__(self, master: str, robot: str, token: str, data_dir: Path, *extra: str) -> None:
        self.command = [str(BIN / "bridgeos-agent"), "run", "--master", master, "--robot", robot, "--token", token]
        self.command += ["--data-dir", str(data_dir), "--firewall", "off", *extra]
        self.data_dir = data_dir
        self.starts = 0
        self.process: subprocess.Popen[bytes] | None = None

    def log_path(self, start: int | None = None) -> Path:
        return self.data_dir.parent / f"agent-{start or self.starts}.log"

    def start(self) -> None:
        self.starts += 1
        with self.log_path().open("wb") as out:
            self.process = subprocess.Popen(self.command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT)

    def kill(self) -> None:
        """kill -9 the agent process alone: the components it started run on in their own sessions."""
        if self.process is not None:
            self.process.kill()
            self.process.wait(10)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(20)
            except subprocess.TimeoutExpired:
                self.kill()

    def log(self) -> str:
        return "".join(self.log_path(n).read_text(errors="replace") for n in range(1, self.starts + 1))


# --------------------------------------------------------------------------- a fleet of real agents


class Fleet:
    """Several real Robot Controllers in one process, reporting what each sent, owes and whether it is connected."""

    def __init__(self, master: str, robots: list[tuple[str, str]], workdir: Path, *, sample_interval: float = 0.2):
        self.workdir = workdir
        self.status_path = workdir / "fleet-status.json"
        self.spec = {
            "master": master,
            "robots": robots,
            "data_dir": str(workdir / "agents"),
            "status": str(self.status_path),
            "sample_interval": sample_interval,
        }
        (workdir / "fleet.json").write_text(json.dumps(self.spec))
        self.process: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        with (self.workdir / "fleet.log").open("ab") as out:
            self.process = subprocess.Popen(
                [PYTHON, "-m", "benchmarks.chaos._rig", "fleet", str(self.workdir / "fleet.json")],
                cwd=ROOT,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def status(self) -> dict[str, dict[str, Any]]:
        """Return per robot: sent (metric points), owed (frames not acked), connected, connected_at (wall time)."""
        if self.process is not None and self.process.poll() is not None and self.process.returncode not in (0, -15):
            raise RuntimeError(f"the fleet exited with {self.process.returncode}:\n{self.log_tail()}")
        try:
            return json.loads(self.status_path.read_text())
        except (OSError, ValueError):
            return {}

    def all_connected(self, since: float = 0.0) -> bool:
        status = self.status()
        return len(status) == len(self.spec["robots"]) and all(
            s["connected"] and s["connected_at"] > since for s in status.values()
        )

    def wait_connected(self, *, since: float = 0.0, timeout: float = 60.0) -> float:
        """Wait until every robot is connected on a connection made after ``since``; return the last one's time."""
        eventually(lambda: self.all_connected(since), timeout=timeout, what="every robot connected")
        return max(s["connected_at"] for s in self.status().values())

    def quiesce(self) -> None:
        """Stop making new metrics (the robots stay connected and keep delivering what they owe)."""
        assert self.process is not None
        self.process.send_signal(signal.SIGUSR1)
        eventually(lambda: all(s.get("quiet") for s in self.status().values()), timeout=10, what="fleet quiet")

    def wait_delivered(self, timeout: float = 60.0) -> None:
        """Wait until no robot owes the cloud a frame."""
        eventually(
            lambda: all(s["owed"] == 0 and s["connected"] for s in self.status().values()),
            timeout=timeout,
            what="every robot's backlog acked",
        )

    def sent(self) -> int:
        return sum(s["sent"] for s in self.status().values())

    def owed(self) -> int:
        return sum(s["owed"] for s in self.status().values())

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            kill_group(self.process, signal.SIGTERM)
            kill_group(self.process)

    def log_tail(self, chars: int = 3000) -> str:
        path = self.workdir / "fleet.log"
        return path.read_text(errors="replace")[-chars:] if path.exists() else ""


async def _host_fleet(spec: dict[str, Any]) -> None:
    """Run one Robot Controller per robot of the spec until SIGTERM, writing their status every 50 ms."""
    from bridgeos_agent.agent import settings_from_args
    from bridgeos_agent.cli import build_parser
    from bridgeos_agent.controller import RobotController

    parser = build_parser()
    controllers: dict[str, RobotController] = {}
    for robot, token in spec["robots"]:
        args = parser.parse_args(
            [
                *("run", "--master", spec["master"], "--robot", robot, "--token", token),
                *("--simulate", "--firewall", "off", "--sample-interval", str(spec["sample_interval"])),
                *("--data-dir", str(Path(spec["data_dir"]) / robot)),
            ]
        )
        controllers[robot] = RobotController(settings_from_args(args), plugins={})
    loop = asyncio.get_running_loop()
    stopping = asyncio.Event()
    quiet = asyncio.Event()
    loop.add_signal_handler(signal.SIGTERM, stopping.set)
    loop.add_signal_handler(signal.SIGUSR1, quiet.set)
    runs = [loop.create_task(c.run(), name=f"agent {robot}") for robot, c in controllers.items()]
    connected_at = dict.fromkeys(controllers, 0.0)
    was_connected = dict.fromkeys(controllers, False)
    status_path = Path(spec["status"])
    quieted = False
    while not stopping.is_set():
        if quiet.is_set() and not quieted:
            # The resource monitor is the only source of metrics: without it a robot only delivers what it owes.
            for task in asyncio.all_tasks():
                if task.get_name() == "monitor":
                    task.cancel()
            quieted = True
        now = time.time()
        status = {}
        for robot, controller in controllers.items():
            connected = controller.connected.is_set()
            if connected and not was_connected[robot]:
                connected_at[robot] = now
            was_connected[robot] = connected
            status[robot] = {
                "sent": controller.metric_points_sent,
                "owed": len(controller.outbox),
                "connected": connected,
                "connected_at": connected_at[robot],
                "quiet": quieted,
            }
        temp = status_path.with_suffix(".tmp")
        temp.write_text(json.dumps(status))
        temp.replace(status_path)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(stopping.wait(), 0.05)
    for controller in controllers.values():
        controller.stop()
    await asyncio.gather(*runs, return_exceptions=True)


def main(argv: list[str]) -> None:
    import argparse

    parser = argparse.ArgumentParser(prog="python -m benchmarks.chaos._rig")
    commands = parser.add_subparsers(dest="command", required=True)
    robots = commands.add_parser("robots", help="create robots and print [[id, token], ...]")
    robots.add_argument("--prefix", required=True)
    robots.add_argument("--count", type=int, required=True)
    fleet = commands.add_parser("fleet", help="host the agents of a fleet spec")
    fleet.add_argument("spec", type=Path)
    commands.add_parser("api-token", help="print a REST API token of the robots' owner")
    args = parser.parse_args(argv)
    if args.command == "robots":
        print(json.dumps(_create_robots_here(args.prefix, args.count)))
    elif args.command == "api-token":
        print(_api_token_here())
    else:
        logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(message)s", stream=sys.stderr)
        asyncio.run(_host_fleet(json.loads(args.spec.read_text())))


if __name__ == "__main__":
    sys.path.insert(0, str(ROOT))
    main(sys.argv[1:])
