"""Reach a Docker engine: open a client sized to a thread pool, follow a robot's container deaths.

Shared by the robot's DockerRuntime and the cloud's Docker and Swarm runtimes.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import functools
import logging
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import docker.utils
from docker.api import APIClient

__all__ = ["LABEL_ROBOT", "DeathFollower", "Deaths", "open_client"]

logger = logging.getLogger(__name__)

LABEL_ROBOT = "io.bridgeos.robot"


class Deaths:
    """Hand each container death the follower reports to whoever waits for it, even if it came first."""

    def __init__(self, remembered: int = 256) -> None:
        self._waiters: dict[str, asyncio.Future[int | None]] = {}
        # Deaths nobody waited for yet (e.g. between listing and watching an adopted container).
        self._unclaimed: collections.OrderedDict[str, int | None] = collections.OrderedDict()
        self._remembered = remembered

    def expect(self, container_id: str) -> asyncio.Future[int | None]:
        """Return a future resolved with the container's exit code when it dies."""
        future: asyncio.Future[int | None] = asyncio.get_running_loop().create_future()
        if container_id in self._unclaimed:
            future.set_result(self._unclaimed.pop(container_id))
        else:
            self._waiters[container_id] = future
        return future

    def forget(self, container_id: str) -> None:
        """Stop waiting for a container's death (it was never started, or we stop it)."""
        self._waiters.pop(container_id, None)

    def forget_unclaimed(self, container_id: str) -> None:
        """Drop a death nobody will wait for (the container is removed)."""
        self._unclaimed.pop(container_id, None)

    def watched(self) -> list[str]:
        """Return the containers whose death someone waits for."""
        return list(self._waiters)

    def died(self, container_id: str, code: int | None) -> None:
        """Deliver a container's death to whoever waits for it, or keep it for a later wait."""
        future = self._waiters.pop(container_id, None)
        if future is not None and not future.done():
            future.set_result(code)
            return
        self._unclaimed[container_id] = code
        while len(self._unclaimed) > self._remembered:
            self._unclaimed.popitem(last=False)


class DeathFollower:
    """Follow the robot's container 'die' events in one thread and hand them to the loop."""

    def __init__(
        self,
        robot: str,
        loop: asyncio.AbstractEventLoop,
        on_die: Callable[[str, int | None], None],
        on_reconnect: Callable[[], None],
    ) -> None:
        self._robot = robot
        self._loop = loop
        self._on_die = on_die
        self._on_reconnect = on_reconnect
        self._closed = threading.Event()
        self._stream: Any = None
        self._thread: threading.Thread | None = None

    def start(self, api: APIClient) -> None:
        """Start following; events since this moment are delivered even if the stream lags."""
        if self._thread is not None:
            return
        self._thread = threading.Thread(
            target=self._run, args=(api, time.time()), name=f"bridgeos-docker-events-{self._robot}", daemon=True
        )
        self._thread.start()

    def _run(self, api: APIClient, since: float) -> None:
        """Read the event stream, reconnecting with backoff when Docker goes away."""
        last_nano = 0
        delay = 0.5
        connected_before = False
        filters = {"type": "container", "event": "die", "label": f"{LABEL_ROBOT}={self._robot}"}
        while not self._closed.is_set():
            try:
                self._stream = api.events(since=f"{since:.9f}", filters=filters, decode=True)
                if self._closed.is_set():  # closed while connecting: close() saw no stream
                    self._stream.close()
                    break
                if connected_before:
                    self._post(self._on_reconnect)
                connected_before = True
                delay = 0.5
                for event in self._stream:
                    nano = int(event.get("timeNano") or 0)
                    if nano and nano <= last_nano:
                        continue  # replayed after a reconnect
                    last_nano = max(last_nano, nano)
                    since = nano / 1e9 if nano else since
                    code = (event.get("Actor") or {}).get("Attributes", {}).get("exitCode")
                    self._post(self._on_die, event.get("id", ""), int(code) if code is not None else None)
            except Exception as exc:
                if not self._closed.is_set():
                    logger.warning("Docker event stream failed (%s); reconnecting in %.1f s", exc, delay)
            if self._closed.wait(delay):
                break
            delay = min(delay * 2, 10.0)

    def _post(self, callback: Callable[..., None], *args: Any) -> None:
        """Run a callback in the event loop, unless the loop is gone."""
        with contextlib.suppress(RuntimeError):
            self._loop.call_soon_threadsafe(callback, *args)

    async def close(self) -> None:
        """Stop following and wait for the thread to end."""
        self._closed.set()
        stream = self._stream
        if stream is not None:
            with contextlib.suppress(Exception):
                stream.close()
        if self._thread is not None:
            await asyncio.to_thread(self._thread.join, 5.0)


async def open_client(
    docker_url: str | None, workers: int, executor: ThreadPoolExecutor
) -> tuple[APIClient, str | None]:
    """Connect to the engine (``docker_url``, else DOCKER_HOST, else its socket) with a pool for ``workers``.

    Return the client and the engine's unix socket path (None over TCP); raise DockerException.
    """
    options: dict[str, Any] = docker.utils.kwargs_from_env()
    if docker_url:
        options["base_url"] = docker_url
    url = options.get("base_url") or "unix:///var/run/docker.sock"
    socket_path = url.removeprefix("unix://") if url.startswith("unix://") else None
    options.update(version="auto", max_pool_size=workers + 2)
    api = await asyncio.get_running_loop().run_in_executor(executor, functools.partial(APIClient, **options))
    return api, socket_path
