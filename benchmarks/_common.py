"""Small helpers shared by the benchmarks: the repo root, a daphne of their own, /proc readings."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
CLK_TCK = os.sysconf("SC_CLK_TCK")


def log(message: str) -> None:
    """Print a progress line on stderr."""
    print(f"[{time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def free_port() -> int:
    """Return a TCP port nobody listens on right now."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def percentile(values: list[float], q: float) -> float | None:
    """Return the q-th percentile (0-100) by nearest rank, or None for no values."""
    if not values:
        return None
    ordered = sorted(values)
    rank = max(0, min(len(ordered) - 1, round(q / 100 * len(ordered) + 0.5) - 1))
    return ordered[rank]


def ensure_postgres_database(url: str) -> None:
    """Create the database a postgres:// URL names, if missing."""
    import psycopg
    from psycopg import sql
    from psycopg.conninfo import conninfo_to_dict, make_conninfo

    params = conninfo_to_dict(url)
    name = params.get("dbname")
    if not name:
        raise SystemExit(f"the database URL names no database: {url}")
    admin = make_conninfo(**{**params, "dbname": "postgres"})
    with psycopg.connect(admin, autocommit=True, connect_timeout=10) as conn:
        if conn.execute("SELECT 1 FROM pg_database WHERE datname = %s", [name]).fetchone() is None:
            conn.execute(sql.SQL("CREATE DATABASE {}").format(sql.Identifier(name)))
            log(f"created database {name}")


def setup_django(env: dict[str, str]) -> None:
    """Point this process at the benchmark's services and set Django up."""
    os.environ.update(env)
    os.environ["DJANGO_SETTINGS_MODULE"] = "bridgeos_cloud.settings"
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    import django

    django.setup()


def migrate(env: dict[str, str]) -> None:
    """Run manage.py migrate against the benchmark's database."""
    subprocess.run(
        [sys.executable, str(ROOT / "manage.py"), "migrate", "--noinput", "-v", "0"],
        cwd=ROOT,
        env={**os.environ, **env},
        check=True,
    )


class ServerProcess:
    """A server the benchmark started on a free port: its process, log, readiness and CPU."""

    name = "server"
    port: int
    pid: int
    process: subprocess.Popen
    log_path: Path

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    def wait(self, timeout: float = 60.0) -> None:
        """Wait until the server accepts connections, failing early if it died."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"{self.name} exited with {self.process.returncode}:\n{self.log_tail()}")
            try:
                socket.create_connection(("127.0.0.1", self.port), timeout=0.2).close()
                return
            except OSError:
                time.sleep(0.05)
        raise TimeoutError(f"{self.name} did not listen on {self.port} within {timeout} s:\n{self.log_tail()}")

    def stop(self, timeout: float = 15.0) -> None:
        """Stop the server: TERM, then KILL after ``timeout`` seconds (daphne may take 15 s to close its sockets)."""
        if self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()

    def log_tail(self, chars: int = 3000) -> str:
        try:
            return self.log_path.read_text(errors="replace")[-chars:]
        except OSError:
            return ""

    def cpu_seconds(self) -> float:
        """Return the user + system CPU time the server used so far (all its threads)."""
        fields = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / CLK_TCK


class Daphne(ServerProcess):
    """A daphne of the benchmark's own, started with scripts/daphne on a free port."""

    name = "daphne"

    def __init__(self, env: dict[str, str], log_path: Path) -> None:
        self.port = free_port()
        self.log_path = log_path
        venv = Path(sys.executable).parent.parent
        with log_path.open("wb") as out:
            self.process = subprocess.Popen(
                [str(ROOT / "scripts" / "daphne"), "-b", "127.0.0.1", "-p", str(self.port)],
                cwd=ROOT,
                env={**os.environ, **env, "VIRTUAL_ENV": str(venv), "PYTHONUNBUFFERED": "1"},
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        # scripts/daphne execs, so this pid is the daphne Python process itself.
        self.pid = self.process.pid

    def memory_mib(self) -> tuple[float, float]:
        """Return daphne's resident memory now and at its peak, in MiB."""
        values = {}
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            key, _, rest = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                values[key] = int(rest.split()[0]) / 1024
        return values.get("VmRSS", 0.0), values.get("VmHWM", 0.0)


class CeleryWorker:
    """A Celery worker of the benchmark's own queue, in a process group of its own."""

    def __init__(self, env: dict[str, str], queue: str, log_path: Path, *, concurrency: int = 2) -> None:
        self.queue = queue
        self.name = f"{queue}@localhost"
        command = [str(Path(sys.executable).parent / "celery"), "-A", "bridgeos_cloud", "worker", "-P", "prefork"]
        command += ["-c", str(concurrency), "-l", "warning", "-n", self.name, "-Q", queue, "--without-gossip"]
        with log_path.open("wb") as out:
            self.process = subprocess.Popen(
                command,
                cwd=ROOT,
                env={**os.environ, **env},
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def wait(self, timeout: float = 60.0) -> None:
        """Return once the worker answers a ping."""
        from bridgeos_cloud.celery import app

        deadline = time.monotonic() + timeout
        while not app.control.ping(destination=[self.name], timeout=0.5):
            if self.process.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("the Celery worker did not start")

    def stop(self) -> None:
        """Stop the worker and its pool: TERM, then KILL after 30 s."""
        try:
            os.killpg(self.process.pid, signal.SIGTERM)
            self.process.wait(30)
        except ProcessLookupError:
            pass
        except subprocess.TimeoutExpired:
            os.killpg(self.process.pid, signal.SIGKILL)
            self.process.wait(10)
