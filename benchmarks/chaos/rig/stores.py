"""Stores of a scenario's own to break (a redis-server, a PostgreSQL cluster), and what PostgreSQL holds."""

from __future__ import annotations

import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import psycopg

from benchmarks._common import free_port
from benchmarks.chaos.rig.base import kill_group, listening, wait_until

PG_BIN = Path(os.environ.get("BRIDGEOS_PG_BIN", "/usr/lib/postgresql/15/bin"))


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
        wait_until(lambda: listening("127.0.0.1", self.port), f"redis-server on {self.port}", 10)

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
