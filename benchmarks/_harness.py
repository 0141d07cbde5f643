"""One harness for what the benchmarks repeat: their flags, a cloud of their own, fleets, ROS 1, the last line.

A benchmark's main reads::

    parser = arguments(__doc__, "200 robots for 15 s: under a minute in all", database="bridgeos_bench", redis=12)
    args = parser.parse_args()
    with cloud(args, "bridgeos-bench-") as bench:
        tokens = create_fleet(owner, 100, "bench-")
        daphne = bench.start_daphne()
        ...
    report(figures)
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing as mp
import os
import shutil
import subprocess
import sys
import tempfile
import time
import xmlrpc.client
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))  # imported as benchmarks._harness too (vpn.py)

from _common import ROOT, CeleryWorker, Daphne, ensure_postgres_database, free_port, log, migrate, setup_django

HOST_PYTHON = "/usr/bin/python3"  # Debian's interpreter, where rospy lives
POSTGRES = "postgres://postgres@127.0.0.1:5432/"
REDIS = "redis://127.0.0.1:6379/"


# --------------------------------------------------------------------------- flags and the last line


def arguments(
    doc: str | None, quick: str, *, database: str | None = None, redis: int | None = None, whole_doc: bool = False
) -> argparse.ArgumentParser:
    """Return a benchmark's parser: its docstring, --quick, and the URLs of its cloud when it starts one."""
    doc = doc or ""
    if whole_doc:
        parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    else:
        parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help=quick)
    if database is not None:
        parser.add_argument("--database-url", default=POSTGRES + database)
    if redis is not None:
        parser.add_argument("--redis-url", default=f"{REDIS}{redis}")
    return parser


def report(figures: dict[str, Any]) -> None:
    """Print the figures as the one JSON object of the benchmark's last line."""
    print(json.dumps(figures), flush=True)


def machine_load() -> str:
    """Describe the machine's load, for the log beside the figures."""
    one, five, _ = os.getloadavg()
    return f"load average {one:.2f} (1 min) {five:.2f} (5 min) on {os.cpu_count()} cores"


def stop_process(process: subprocess.Popen[Any], timeout: float = 10) -> None:
    """Stop a child: TERM, then KILL if it is still there after ``timeout`` seconds."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(10)


# --------------------------------------------------------------------------- a cloud of the benchmark's own


class Cloud:
    """A cloud of the benchmark's own: its database, Redis and data directory, and what it started on them."""

    def __init__(self, env: dict[str, str], data_dir: Path, stop_timeout: float) -> None:
        self.env = env
        self.data_dir = data_dir
        self.daphnes: list[Daphne] = []
        self.workers: list[CeleryWorker] = []
        self.processes: list[subprocess.Popen[bytes]] = []
        self.stop_timeout = stop_timeout

    def start_daphne(self, log_name: str = "daphne.log", *, wait: bool = True) -> Daphne:
        """Start a daphne on a free port, logging to the data directory; wait until it listens unless told not to."""
        daphne = Daphne(self.env, self.data_dir / log_name)
        self.daphnes.append(daphne)
        if wait:
            daphne.wait()
        return daphne

    def start_celery(self, queue: str, *, concurrency: int = 2, wait: bool = True) -> CeleryWorker:
        """Start a Celery worker on a queue of the benchmark's own; wait until it answers unless told not to."""
        worker = CeleryWorker(self.env, queue, self.data_dir / "worker.log", concurrency=concurrency)
        self.workers.append(worker)
        if wait:
            worker.wait()
        return worker

    def start_process(
        self, name: str, argv: Sequence[str], env: dict[str, str] | None = None
    ) -> subprocess.Popen[bytes]:
        """Start a helper process (a fleet, an agent) in a session of its own, logging to ``name``.log."""
        with (self.data_dir / f"{name}.log").open("wb") as out:
            process = subprocess.Popen(
                list(argv),
                cwd=ROOT,
                env={**os.environ, **self.env, "PYTHONUNBUFFERED": "1", **(env or {})},
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        self.processes.append(process)
        return process

    def start_agent(
        self, daphne: Daphne, robot_id: str, token: str, *flags: str, env: dict[str, str] | None = None
    ) -> subprocess.Popen[bytes]:
        """Start `bridgeos-agent run` for one robot against a daphne, its data under the data directory."""
        argv = [str(Path(sys.executable).parent / "bridgeos-agent"), "run", "--master", daphne.ws_url]
        argv += ["--robot", robot_id, "--token", token, "--data-dir", str(self.data_dir / "agent"), *flags]
        return self.start_process("agent", argv, env)

    def stop(self) -> None:
        """Stop what was started: the helpers, then the workers, then the daphnes (a second call does nothing)."""
        for process in reversed(self.processes):
            stop_process(process, 15)
        for worker in reversed(self.workers):
            worker.stop()
        for daphne in self.daphnes:
            daphne.stop(timeout=self.stop_timeout)
        self.processes, self.workers = [], []

    def log_tails(self) -> None:
        """Log the end of every daphne's log, to show why a run failed."""
        for daphne in self.daphnes:
            log(f"daphne {daphne.pid} log tail:\n{daphne.log_tail()}")

    def log_errors(self) -> None:
        """Log how many error lines each daphne wrote, if any."""
        for daphne in self.daphnes:
            errors = [line for line in daphne.log_tail(200_000).splitlines() if "Traceback" in line or "ERROR" in line]
            if errors:
                log(f"daphne logged {len(errors)} error line(s); see {daphne.log_path}")


@contextlib.contextmanager
def cloud(
    args: argparse.Namespace,
    prefix: str,
    *,
    env: dict[str, str] | None = None,
    flush_redis: bool = True,
    migrate_here: bool = False,
    stop_timeout: float = 15.0,
    remove_data: bool = False,
) -> Iterator[Cloud]:
    """Ready the benchmark's database and Redis, set Django up on them, and stop what it started at the end.

    ``args`` carries ``database_url`` and, unless the cloud runs without Redis, ``redis_url``.
    ``flush_redis`` empties the Redis database first; ``migrate_here`` migrates in this process (one
    Django start less) instead of in a subprocess; ``stop_timeout`` is how long a daphne may take to
    stop before it is killed; ``remove_data`` deletes the data directory at the end.
    """
    data_dir = Path(tempfile.mkdtemp(prefix=prefix))
    redis_url = getattr(args, "redis_url", "")
    full_env = {"DATABASE_URL": args.database_url, "REDIS_URL": redis_url, "BRIDGEOS_DATA_DIR": str(data_dir)}
    full_env.update(env or {})
    bench = Cloud(full_env, data_dir, stop_timeout)
    try:
        ensure_postgres_database(args.database_url)
        if flush_redis and redis_url:
            import redis

            redis.Redis.from_url(redis_url).flushdb()
        if migrate_here:
            setup_django(full_env)
            from django.core.management import call_command

            call_command("migrate", interactive=False, verbosity=0)
        else:
            migrate(full_env)
            setup_django(full_env)
        try:
            yield bench
        except BaseException:
            bench.log_tails()
            raise
        finally:
            bench.stop()
        bench.log_errors()
    finally:
        if remove_data:
            shutil.rmtree(data_dir, ignore_errors=True)


# --------------------------------------------------------------------------- fleets


def forget_fleet(prefix: str, *, metrics: bool = False, events: bool = False) -> None:
    """Delete the robots of an earlier run; their ingested frame ids, metric and event rows first, by straight SQL."""
    from django.db import connection

    from monitoring.models import Event, IngestedFrame, Metric
    from robots.models import Robot

    with connection.cursor() as cursor:
        # Straight SQL: a cascade through the ORM would walk every old metric row. The frame ids go
        # always: a new robot of the same id sends the same ids again, and they would be taken for
        # resends of frames already stored, acked and never stored.
        for wanted, model in ((True, IngestedFrame), (metrics, Metric), (events, Event)):
            if wanted:
                cursor.execute(f"DELETE FROM {model._meta.db_table} WHERE robot_id LIKE %s", [prefix + "%"])
    Robot.objects.filter(id__startswith=prefix).delete()


def create_fleet(
    owner: Any,
    count: int,
    prefix: str,
    *,
    digits: int = 4,
    named: bool = False,
    skills: Sequence[dict[str, Any]] = (),
    batch_size: int | None = None,
    organization: Any = None,
) -> list[tuple[str, str]]:
    """Bulk-create ``count`` robots (in the owner's personal organization unless told), with tokens and Skills."""
    from robots.models import Robot, default_robot_config
    from skills.models import Component, Skill
    from teams.services import personal_organization

    config = default_robot_config()
    organization = organization or personal_organization(owner)
    rows, tokens = [], []
    for i in range(count):
        robot = Robot(id=f"{prefix}{i:0{digits}d}", owner=owner, config=config, organization=organization)
        if named:
            robot.name = f"Bench robot {i}"
        tokens.append((robot.id, robot.issue_token()))
        rows.append(robot)
    Robot.objects.bulk_create(rows, batch_size=batch_size)
    if skills:
        # The Skill's rows written directly: add_skill validates each config, which is not measured here.
        created = Skill.objects.bulk_create(
            Skill(robot=robot, skill_id=c["skill_id"], name=c["skill"], config=c) for robot in rows for c in skills
        )
        Component.objects.bulk_create(
            Component(skill=skill, component_id=cid, location=c["location"], resources=c.get("resources", {}))
            for skill in created
            for cid, c in skill.config["components"].items()
        )
    return tokens


class Clients:
    """Client processes forked before any event loop runs, a share of the fleet each.

    Each runs ``target(index, share, start_event, stop_event, results, *args)``: it may wait for
    ``start_event``, runs until ``stop_event``, and puts one report on ``results``.
    """

    def __init__(self, target: Callable[..., None], shares: Sequence[Any], *args: Any) -> None:
        ctx = mp.get_context("fork")
        self.start_event, self.stop_event, self.results = ctx.Event(), ctx.Event(), ctx.Queue()
        self.processes = [
            ctx.Process(
                target=target,
                args=(index, share, self.start_event, self.stop_event, self.results, *args),
                daemon=True,
            )
            for index, share in enumerate(shares)
        ]
        for process in self.processes:
            process.start()

    def reports(self, timeout: float) -> list[dict[str, Any]]:
        """Collect every process's report, then let them exit."""
        reports = [self.results.get(True, timeout) for _ in self.processes]
        for process in self.processes:
            process.join(timeout=30)
        return reports

    def kill(self) -> None:
        """Kill the processes still running."""
        for process in self.processes:
            if process.is_alive():
                process.kill()
                process.join()


def shares(items: Sequence[Any], count: int) -> list[Sequence[Any]]:
    """Deal items to ``count`` shares in turn."""
    return [items[p::count] for p in range(count)]


# --------------------------------------------------------------------------- ROS 1


def ros_env(master: str, home: str | Path, namespace: str | None = None) -> dict[str, str]:
    """Return a clean environment for Debian's ROS python, free of the venv."""
    env = {
        "PATH": "/usr/bin:/bin",
        "HOME": str(home),
        "LANG": "C.UTF-8",
        "ROS_MASTER_URI": master,
        "ROS_IP": "127.0.0.1",
        "ROS_HOME": str(home),
        "PYTHONUNBUFFERED": "1",
        "PYTHONWARNINGS": "ignore",
    }
    if namespace:
        env["ROS_NAMESPACE"] = namespace
    return env


@contextlib.contextmanager
def rosmaster(home: str | Path) -> Iterator[str]:
    """Run a private ROS master for the benchmark; yield its URI."""
    port = free_port()
    uri = f"http://127.0.0.1:{port}"
    process = subprocess.Popen(
        [HOST_PYTHON, "/usr/bin/rosmaster", "--core", "-p", str(port)],
        env=ros_env(uri, home),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 30
        while True:
            try:
                xmlrpc.client.ServerProxy(uri).getPid("/bench")
                break
            except OSError:
                if process.poll() is not None or time.monotonic() > deadline:
                    raise SystemExit("the private rosmaster did not start") from None
                time.sleep(0.1)
        yield uri
    finally:
        process.kill()
        process.wait(10)
