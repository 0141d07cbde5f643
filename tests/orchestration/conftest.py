"""A cloud of a test module's own: daphne and a Celery worker on a queue, a cloud id and a runtime of their own.

Every object the stack creates carries the module's cloud id (``wt-cloud-<hex>``), so the
teardown removes exactly those (services, containers, processes, networks, volume
directories) and no other engineer's or test run's. The worker runs in a process group of
its own, so killing it kills its pool children with it.
"""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from asgiref.sync import sync_to_async

# nodes and rosmaster: the agent tests' fixtures, for the modules here that run rospy nodes too.
from tests.agent.conftest import Cloud, nodes, rosmaster  # noqa: F401
from tests.conftest import BIN, ROOT, close_other_sessions, remove_cloud_copies, service_env
from tests.logguard import watch


@dataclass
class Stack:
    """One cloud: its id, runtime, Celery queue, daphne and worker."""

    cloud_id: str
    runtime: str
    queue: str
    env: dict[str, str]
    server: Cloud
    logs: Path
    worker: subprocess.Popen | None = None
    workers_started: int = 0
    volumes: Path = field(default_factory=Path)

    @property
    def ws_url(self) -> str:
        return self.server.ws_url

    @property
    def url(self) -> str:
        return self.server.url

    def start_worker(self, concurrency: int = 2) -> None:
        """Start a prefork worker on the stack's queue, in a process group of its own, and wait for it."""
        from django.conf import settings

        from bridgeos_cloud.celery import app

        self.workers_started += 1
        name = f"{self.queue}-{self.workers_started}@localhost"
        log = watch(self.logs / f"worker-{self.workers_started}.log")
        env = {**service_env(settings.DATABASES["default"]["NAME"]), **self.env}
        command = [str(BIN / "celery"), "-A", "bridgeos_cloud", "worker", "-P", "prefork", "-c", str(concurrency)]
        command += ["-l", "info", "-n", name, "-Q", self.queue, "--without-gossip", "--without-mingle"]
        with log.open("wb") as out:
            self.worker = subprocess.Popen(
                command,
                cwd=ROOT,
                env=env,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        deadline = time.monotonic() + 60
        while not app.control.ping(destination=[name], timeout=0.5):
            if self.worker.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"Celery worker did not start; its log:\n{log.read_text()[-3000:]}")

    def kill_worker(self) -> None:
        """Kill the worker and its pool children at once (SIGKILL to the group): a crash, not a shutdown."""
        if self.worker is not None and self.worker.poll() is None:
            os.killpg(self.worker.pid, signal.SIGKILL)
            self.worker.wait(15)
        self.worker = None

    def stop_worker(self) -> None:
        """Stop the worker politely, then make sure nothing of its group is left."""
        if self.worker is None:
            return
        if self.worker.poll() is None:
            self.worker.terminate()
            try:
                self.worker.wait(20)
            except subprocess.TimeoutExpired:
                pass
        try:
            os.killpg(self.worker.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.worker.wait(15)
        self.worker = None

    def reconcile(self, timeout: float = 90.0) -> dict[str, int]:
        """Run one reconciler round on the stack's worker and return what it did."""
        from skills.tasks import reconcile_cloud

        return reconcile_cloud.apply_async(queue=self.queue).get(timeout=timeout)

    def worker_log(self) -> str:
        return "".join(path.read_text(errors="replace")[-4000:] for path in sorted(self.logs.glob("worker-*.log")))


def observe(runtime: str) -> list[Any]:
    """List what this test cloud runs on the engine."""
    from skills.cloud.orchestration import with_runtime

    return with_runtime("observer", lambda cloud_runtime: cloud_runtime.observe(), name=runtime)


@sync_to_async
def observe_async(runtime: str) -> list[Any]:
    return observe(runtime)


def make_stack(runtime: str, tmp: Path, **extra: str) -> Iterator[Stack]:
    """Start daphne and a worker for a cloud of its own, and remove all it ran afterwards."""
    from django.conf import settings

    cloud_id = f"wt-cloud-{uuid.uuid4().hex[:10]}"
    queue = f"{cloud_id}-q"
    volumes = tmp / "volumes"
    port_base = 42000 + (int(cloud_id[-4:], 16) % 140) * 50
    env = {
        "BRIDGEOS_CLOUD_ID": cloud_id,
        "BRIDGEOS_CLOUD_RUNTIME": runtime,
        "BRIDGEOS_CLOUD_VOLUMES_DIR": str(volumes),
        "BRIDGEOS_CLOUD_ROS_MASTER_PORTS": f"{port_base}-{port_base + 49}",
        "BRIDGEOS_CLOUD_START_TIMEOUT_S": "60",
        "BRIDGEOS_CLOUD_RESTART_BACKOFF_MAX_S": "2",
        "CELERY_TASK_DEFAULT_QUEUE": queue,
        # A task of a killed worker comes back within the test, not after an hour.
        "CELERY_VISIBILITY_TIMEOUT_S": "20",
        **extra,
    }
    overrides = {
        "CLOUD_ID": cloud_id,
        "CLOUD_RUNTIME": runtime,
        "CLOUD_VOLUMES_DIR": str(volumes),
        "CLOUD_ROS_MASTER_PORTS": env["BRIDGEOS_CLOUD_ROS_MASTER_PORTS"],
    }
    saved = {key: settings.BRIDGEOS[key] for key in overrides}
    settings.BRIDGEOS.update(overrides)
    logs = tmp / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    server = Cloud(logs / "daphne.log")
    server.env = env
    stack = Stack(cloud_id, runtime, queue, env, server, logs, volumes=volumes)
    try:
        server.start()
        stack.start_worker()
        yield stack
    finally:
        stack.stop_worker()
        server.stop()
        try:
            remove_cloud_copies(runtime)
            _remove_networks(runtime)
        finally:
            settings.BRIDGEOS.update(saved)
            shutil.rmtree(volumes, ignore_errors=True)


def _remove_networks(runtime: str) -> None:
    """Remove the test cloud's networks, waiting while Swarm still detaches removed copies from them."""
    from skills.cloud.orchestration import with_runtime

    async def sweep(cloud_runtime) -> int:
        for name in (await cloud_runtime.networks()).values():
            await cloud_runtime.remove_network_named(name)
        return len(await cloud_runtime.networks())

    deadline = time.monotonic() + 20
    while with_runtime("cleanup", sweep, name=runtime) and time.monotonic() < deadline:
        time.sleep(0.25)


@pytest.fixture(scope="session", autouse=True)
def sessions_closed_at_the_end(django_db_setup, django_db_blocker) -> Iterator[None]:
    """End every other session on the test database once the run is over, so it can be dropped."""
    yield
    with django_db_blocker.unblock():
        close_other_sessions()


@pytest.fixture
def robots_disconnect_before_flush(transactional_db) -> Iterator[None]:
    """After the test: wait until daphne recorded every robot gone (before tables are flushed), then
    remove what the test's robots ran, networks too (the next test's robot gets the same subnet)."""
    yield
    from robots.models import Robot
    from skills.cloud.runtime import runtime_name

    deadline = time.monotonic() + 15
    while Robot.objects.filter(connected=True).exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.1)
    remove_cloud_copies()
    _remove_networks(runtime_name())
