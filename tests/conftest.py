"""Fixtures that start the real parts (daphne on a socket, a Celery worker on Redis) and helpers every test shares."""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from pytest_django.plugin import blocking_manager_key

from tests.fastflush import delete_instead_of_truncate
from tests.flushretry import retry_flush_deadlocks
from tests.logguard import watch

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
_config: pytest.Config


def pytest_configure(config: pytest.Config) -> None:
    global _config
    _config = config
    retry_flush_deadlocks()
    delete_instead_of_truncate()


def free_port() -> int:
    """Return a TCP port nobody listens on right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def wait_for_port(port: int, process: subprocess.Popen, timeout: float = 30.0) -> None:
    """Wait until something accepts on the port, failing early if the process died."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"process exited with {process.returncode} before listening on {port}")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.2).close()
            return
        except OSError:
            time.sleep(0.05)
    raise TimeoutError(f"nothing listened on port {port} within {timeout} s")


def wait_until(check: Callable[[], Any], timeout: float = 15.0, what: str = "condition", interval: float = 0.05) -> Any:
    """Poll a check until it returns something truthy; return that, or fail saying what never happened."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


async def eventually(
    check: Callable[[], Any], timeout: float = 30.0, what: str = "condition", interval: float = 0.05
) -> Any:
    """Poll a check (sync or async) until it returns something truthy; return that, or fail saying what never happened."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if inspect.isawaitable(value):
            value = await value
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        await asyncio.sleep(interval)


class LoopThread:
    """An asyncio loop in a thread of its own, for code under test while blocking clients hold the test's thread."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="test-loop", daemon=True)
        self.thread.start()

    def start(self, coroutine: Any) -> Future[Any]:
        """Schedule a coroutine on the loop and return its future."""
        return asyncio.run_coroutine_threadsafe(coroutine, self.loop)

    def run(self, coroutine: Any, timeout: float = 30) -> Any:
        """Run a coroutine on the loop and return its result."""
        return self.start(coroutine).result(timeout)

    def call(self, function: Callable[[], Any]) -> Any:
        """Call a function on the loop's thread (to build what must belong to the loop) and return its result."""

        async def run() -> Any:
            return function()

        return self.run(run(), timeout=10)

    def stop(self) -> None:
        """Stop the loop and wait for its thread."""
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(5)


def stop_process(process: subprocess.Popen, timeout: float = 10) -> None:
    """Ask a process to end (SIGTERM), and kill it if it has not within ``timeout`` seconds."""
    process.terminate()
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()


def service_env(db_name: str) -> dict[str, str]:
    """Return the environment a server process needs to share the test database."""
    from django.conf import settings

    db = settings.DATABASES["default"]
    if db["ENGINE"] != "django.db.backends.postgresql":
        pytest.fail("The suite runs against PostgreSQL: run it with `make test` (DATABASE_URL=postgres://...).")
    url = f"postgres://{db['USER']}@{db['HOST'] or '127.0.0.1'}:{db['PORT'] or 5432}/{db_name}"
    return {**os.environ, "DATABASE_URL": url, "PYTHONUNBUFFERED": "1"}


@dataclass
class Server:
    """A daphne serving the project on a real socket."""

    host: str
    port: int
    log: Path

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://{self.host}:{self.port}"


@pytest.fixture(scope="session")
def daphne_server(django_db_setup, django_db_blocker, tmp_path_factory) -> Iterator[Server]:
    """Start daphne against the test database; tests that use it need committed data (transactional_db)."""
    from django.conf import settings

    port = free_port()
    log = watch(tmp_path_factory.mktemp("daphne") / "daphne.log")
    env = service_env(settings.DATABASES["default"]["NAME"])
    with log.open("wb") as out:
        process = subprocess.Popen(
            [str(ROOT / "scripts" / "daphne"), "-b", "127.0.0.1", "-p", str(port)],
            cwd=ROOT,
            # A higher frame rate than production's default lets fuzzing send thousands of frames.
            env={**env, "VIRTUAL_ENV": str(BIN.parent), "BRIDGEOS_ROBOT_FRAMES_PER_S": "2000"},
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    try:
        wait_for_port(port, process)
        yield Server("127.0.0.1", port, log)
    finally:
        stop_process(process)
        with django_db_blocker.unblock():
            close_other_sessions()


@contextlib.contextmanager
def another_daphne(log: Path, **env: str) -> Iterator[tuple[Server, subprocess.Popen]]:
    """Start one more daphne sharing the test database and Redis (a second server process of the cloud)."""
    from django.conf import settings

    port = free_port()
    watch(log)
    full_env = service_env(settings.DATABASES["default"]["NAME"]) | {"VIRTUAL_ENV": str(BIN.parent), **env}
    # Another cloud's process (its own id) is not listed among this cloud's: nothing to learn or release.
    ours = "BRIDGEOS_CLOUD_ID" not in env
    listed_before = listed_processes() if ours else set()
    with log.open("wb") as out:
        process = subprocess.Popen(
            [str(ROOT / "scripts" / "daphne"), "-b", "127.0.0.1", "-p", str(port)],
            cwd=ROOT,
            env=full_env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    names: set[str] = set()
    try:
        wait_for_port(port, process)
        if ours:
            names = newly_listed(listed_before)
        yield Server("127.0.0.1", port, log), process
    finally:
        stop_process(process)
        release_processes(names)


def listed_processes() -> set[str]:
    """Return the server processes this cloud lists in Redis (robots/presence.py's registry)."""
    import redis
    from django.conf import settings

    from robots.presence import PROCESSES_KEY, cloud_namespace

    with redis.Redis.from_url(settings.REDIS_URL, socket_timeout=5) as client:
        return {member.decode() for member in client.smembers(PROCESSES_KEY.format(cloud_namespace()))}


def newly_listed(before: set[str], timeout: float = 5.0) -> set[str]:
    """Return the processes listed since ``before``: a daphne registers itself just after it starts listening."""
    deadline = time.monotonic() + timeout
    while not (new := listed_processes() - before) and time.monotonic() < deadline:
        time.sleep(0.05)
    return new


def release_processes(names: set[str]) -> None:
    """Forget stopped server processes and mark offline the robots they still held, before the tables are flushed.

    A stopped daphne leaves its robots for a live process's sweep (every 2 s, or 10 s after a kill),
    and a sweep that writes them while pytest-django truncates the tables deadlocks with it: the
    flush fails. Swept here, before the test ends, they are offline before the flush begins.
    """
    if not names:
        return
    import redis
    from django.conf import settings
    from django.db import connections

    from robots.presence import PROCESS_KEY, sweep_dead_processes

    with redis.Redis.from_url(settings.REDIS_URL, socket_timeout=5) as client:
        client.delete(*(PROCESS_KEY.format(name) for name in names))

    def sweep() -> None:
        try:
            sweep_dead_processes()
        finally:
            connections.close_all()

    # On a thread of its own: an async test's server ends inside its event loop. And unblocked: a
    # module's server ends after its last test, where pytest-django blocks the database.
    with _config.stash[blocking_manager_key].unblock(), ThreadPoolExecutor(1) as thread:
        thread.submit(sweep).result()


def close_other_sessions() -> None:
    """End other sessions on the test database so it can be dropped at the end of the run."""
    from django.db import connection

    with connection.cursor() as cursor:
        cursor.execute(
            "SELECT pg_terminate_backend(pid) FROM pg_stat_activity"
            " WHERE datname = current_database() AND pid <> pg_backend_pid()"
        )


@pytest.fixture(scope="session")
def celery_worker_process(django_db_setup, django_db_blocker, tmp_path_factory) -> Iterator[Path]:
    """Start a real Celery worker on the test Redis database and wait until it answers a ping."""
    import redis
    from django.conf import settings

    from bridgeos_cloud.celery import app

    if not settings.REDIS_URL:
        pytest.fail("The suite needs Redis: run it with `make test` (REDIS_URL=redis://...).")
    # Tasks queued by an earlier, interrupted run must not reach this worker.
    redis.Redis.from_url(settings.REDIS_URL).flushdb()
    log = watch(tmp_path_factory.mktemp("celery") / "worker.log")
    env = service_env(settings.DATABASES["default"]["NAME"])
    name = f"test-{os.getpid()}@localhost"
    with log.open("wb") as out:
        process = subprocess.Popen(
            [str(BIN / "celery"), "-A", "bridgeos_cloud", "worker", "-P", "solo", "-l", "info", "-n", name],
            cwd=ROOT,
            env=env,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    try:
        deadline = time.monotonic() + 60
        while not app.control.ping(destination=[name], timeout=0.5):
            if process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"Celery worker did not start; its log:\n{log.read_text()[-3000:]}")
        yield log
    finally:
        stop_process(process, timeout=15)
        with django_db_blocker.unblock():
            # A task that was still running when its test ended may have launched a copy since.
            remove_cloud_copies()
            close_other_sessions()


def remove_cloud_copies(runtime: str | None = None) -> int:
    """Remove everything the test cloud runs (cloud copies, ROS masters); return how many there were."""
    from skills.cloud.orchestration import with_runtime
    from skills.cloud.relay import remove_relay_processes

    async def sweep(cloud_runtime) -> int:
        found = await cloud_runtime.observe()
        for item in found:
            await cloud_runtime.remove(item)
        return len(found)

    # Cloud relays are host processes whatever the runtime.
    return with_runtime("cleanup", sweep, name=runtime) + remove_relay_processes()


@pytest.fixture(autouse=True)
def no_cloud_copies_left(request):
    """Remove the cloud copies a test's Celery worker launched, so no process outlives the test."""
    yield
    if "celery_worker_process" in request.fixturenames:
        remove_cloud_copies()


@pytest.fixture(autouse=True)
def quiet_server_before_flush(request):
    """Close every robot connection and wait until the server recorded it, before the tables are flushed.

    A test that leaves a robot connected lets the server write its disconnect while
    pytest-django truncates the tables, and the two deadlock. Depending on pytest-django's
    database fixture makes this teardown run before its flush.
    """
    if "daphne_server" not in request.fixturenames:
        yield
        return
    request.getfixturevalue("_django_db_helper")
    yield
    from asgiref.sync import async_to_sync
    from channels.layers import get_channel_layer

    from robots.models import Robot

    layer = get_channel_layer()
    channels = list(Robot.objects.exclude(channel="").values_list("channel", flat=True))
    for channel in channels:
        async_to_sync(layer.send)(channel, {"type": "robot.revoked"})
    online = bool(channels)
    deadline = time.monotonic() + 10
    while Robot.objects.filter(connected=True).exists() and time.monotonic() < deadline:
        online = True
        time.sleep(0.05)
    if online:
        # Let the last disconnect's transaction and broadcast finish. Most tests end with no robot
        # online: for them there is nothing to wait for, and 0.1 s a test added up to half a minute.
        time.sleep(0.1)
