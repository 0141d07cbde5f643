"""One orchestration step at a time per component, across every worker process.

PostgreSQL advisory locks on a connection of their own: held while a step talks to the
engine (seconds), without holding a transaction or a row lock that the robot's reports would
wait behind, and released by PostgreSQL itself when a worker dies mid-step. Elsewhere (the
SQLite of `make run` without a database) a lock file with flock does the same on one host.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import os
import time
from collections.abc import Iterator
from pathlib import Path

import psycopg
from django.conf import settings
from django.db import connections

from monitoring.sinks import conninfo_from_settings

__all__ = ["LockBusy", "orchestration_lock"]


class LockBusy(Exception):
    """Another worker holds the lock for longer than we may wait."""


def _lock_id(key: str) -> int:
    """Map a key to a signed 64-bit advisory lock id."""
    return int.from_bytes(hashlib.sha256(f"bridgeos:{key}".encode()).digest()[:8], "big", signed=True)


@contextlib.contextmanager
def orchestration_lock(key: str, *, wait: float = 30.0) -> Iterator[None]:
    """Hold the lock named ``key`` for the block, waiting up to ``wait`` seconds for it."""
    if connections["default"].vendor == "postgresql":
        with _advisory_lock(key, wait):
            yield
    else:
        with _file_lock(key, wait):
            yield


@contextlib.contextmanager
def _advisory_lock(key: str, wait: float) -> Iterator[None]:
    lock_id = _lock_id(key)
    with psycopg.connect(conninfo_from_settings(), autocommit=True) as conn:
        deadline = time.monotonic() + wait
        delay = 0.02
        while not conn.execute("SELECT pg_try_advisory_lock(%s)", [lock_id]).fetchone()[0]:
            if time.monotonic() >= deadline:
                raise LockBusy(f"{key} is busy in another worker for more than {wait:g} s")
            time.sleep(delay)
            delay = min(delay * 2, 0.25)
        try:
            yield
        finally:
            # Closing the connection releases it too; unlocking first keeps that explicit.
            with contextlib.suppress(psycopg.Error):
                conn.execute("SELECT pg_advisory_unlock(%s)", [lock_id])


@contextlib.contextmanager
def _file_lock(key: str, wait: float) -> Iterator[None]:
    directory = Path(settings.DATA_DIR) / "locks"
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / (hashlib.sha256(key.encode()).hexdigest()[:32] + ".lock")
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        deadline = time.monotonic() + wait
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() >= deadline:
                    raise LockBusy(f"{key} is busy in another worker for more than {wait:g} s") from None
                time.sleep(0.05)
        yield
    finally:
        os.close(fd)
