"""What every part of the rig leans on: where the suite's stores are, waiting, killing, scratch files."""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

PYTHON = sys.executable
BIN = Path(sys.executable).parent


def database_url() -> str:
    """Return the PostgreSQL database the suite's clouds use.

    BRIDGEOS_CHAOS_DATABASE_URL if set, else a database of its own beside the test or dev one (so a
    test run's own database stays untouched), else bridgeos_chaos on this machine.
    """
    explicit = os.environ.get("BRIDGEOS_CHAOS_DATABASE_URL")
    if explicit:
        return explicit
    base = os.environ.get("TEST_DATABASE_URL") or os.environ.get("DATABASE_URL") or ""
    if base.startswith("postgres"):
        return base.rsplit("/", 1)[0] + "/" + base.rsplit("/", 1)[1].split("?")[0] + "_chaos"
    return "postgres://postgres@127.0.0.1:5432/bridgeos_chaos"


def redis_url() -> str:
    """Return the Redis the suite's clouds use when a scenario does not break Redis itself."""
    return (
        os.environ.get("BRIDGEOS_CHAOS_REDIS_URL")
        or os.environ.get("TEST_REDIS_URL")
        or os.environ.get("REDIS_URL")
        or "redis://127.0.0.1:6379/13"
    )


def scratch_dir(name: str) -> Path:
    """Make a fresh temporary directory for one scenario's files."""
    return Path(tempfile.mkdtemp(prefix=f"bridgeos-chaos-{name}-"))


def wait_until(check: Callable[[], Any], what: str, timeout: float, interval: float = 0.05) -> Any:
    """Poll until check() is truthy and return its value; raise TimeoutError saying what did not happen."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise TimeoutError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


def listening(host: str, port: int) -> bool:
    """Tell whether something accepts TCP connections on host:port."""
    try:
        socket.create_connection((host, port), timeout=0.2).close()
    except OSError:
        return False
    return True


def kill_group(process: subprocess.Popen[bytes], sig: int = signal.SIGKILL) -> None:
    """Send a signal to a process started in a session of its own, and to everything it started."""
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, sig)
    with contextlib.suppress(subprocess.TimeoutExpired):
        process.wait(30)


def tail(path: Path, chars: int = 1500) -> str:
    """Return the end of a log file, or nothing if it cannot be read."""
    with contextlib.suppress(OSError):
        return path.read_text(errors="replace")[-chars:]
    return ""
