"""Applied frame ids survive Redis going away and coming back: saved later, never a stuck failure."""

from __future__ import annotations

import asyncio
import shutil
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import redis.exceptions

from robots.dedup import AppliedIds

REDIS_SERVER = shutil.which("redis-server")
pytestmark = pytest.mark.skipif(REDIS_SERVER is None, reason="redis-server is not installed")


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


class PrivateRedis:
    """A redis-server of this test's own, so killing it touches nobody else."""

    def __init__(self, directory: Path) -> None:
        self.port = free_port()
        self.directory = directory
        self.process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        assert REDIS_SERVER is not None
        self.process = subprocess.Popen(
            [REDIS_SERVER, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--dir", str(self.directory)],
            stdout=subprocess.DEVNULL,
        )
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return
            except OSError:
                time.sleep(0.02)
        raise TimeoutError("redis-server did not listen")

    def kill(self) -> None:
        if self.process is not None:
            self.process.kill()
            self.process.wait()
            self.process = None


@pytest.fixture
def redis_server(tmp_path: Path) -> Iterator[PrivateRedis]:
    server = PrivateRedis(tmp_path)
    server.start()
    try:
        yield server
    finally:
        server.kill()


def test_ids_not_saved_while_redis_is_down_are_saved_once_it_is_back(redis_server: PrivateRedis) -> None:
    async def scenario() -> tuple[list[str], list[str]]:
        store = AppliedIds(redis_server.url)
        store.add("r1", "a")
        await store.flush()
        redis_server.kill()
        store.add("r1", "b")
        with pytest.raises(redis.exceptions.ConnectionError):
            await store.flush()
        redis_server.start()
        # The failed write must not fail every later flush (a robot's login loads through one).
        loaded = await store.load("r1")
        store.add("r1", "c")
        await store.flush()
        again = await AppliedIds(redis_server.url).load("r1")
        await store.close()
        return loaded, again

    loaded, again = asyncio.run(scenario())
    # Redis came back empty: what it holds is what was written after, in order, "b" included.
    assert loaded == ["b"]
    assert again == ["b", "c"]
