"""HAProxy in front of a benchmark's daphnes, configured as the stack's (docker/haproxy/haproxy.cfg)."""

from __future__ import annotations

import resource
import shutil
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # imported as benchmarks._balancer too (its test)

from _common import Daphne, ServerProcess, free_port

# Two sockets a proxied connection: as many as the hard limit on open files lets HAProxy hold
# (20,000 here, which a container without CAP_SYS_RESOURCE cannot raise: ~9,900 connections).
OPEN_FILES = resource.getrlimit(resource.RLIMIT_NOFILE)[1]
MAXCONN = (OPEN_FILES - 200) // 2

CONFIG = """\
global
    maxconn {maxconn}
    hard-stop-after 30s

defaults
    mode http
    option redispatch
    retries 2
    timeout connect 3s
    timeout client 60s
    timeout server 60s
    timeout http-request 10s
    # A WebSocket, once upgraded, is a tunnel: robots hold it for hours.
    timeout tunnel 1h
    timeout client-fin 5s

frontend fleet
    bind 127.0.0.1:{port}
    maxconn {maxconn}
    default_backend daphne

backend daphne
    # Long-lived sockets: the process holding the fewest gets the next robot.
    balance leastconn
{servers}
"""


def balancer_capacity() -> int:
    """How many proxied connections one HAProxy may hold here, leaving room for the API's own."""
    return MAXCONN - 100


def _more_open_files() -> None:
    """Let HAProxy open as many files as the hard limit allows (run in the child)."""
    resource.setrlimit(resource.RLIMIT_NOFILE, (OPEN_FILES, OPEN_FILES))


class Balancer(ServerProcess):
    """One HAProxy process on a free port spreading WebSockets over the daphnes, least connections first."""

    name = "haproxy"

    def __init__(self, daphnes: list[Daphne], directory: Path) -> None:
        haproxy = shutil.which("haproxy") or "/usr/sbin/haproxy"
        if not Path(haproxy).exists():
            raise SystemExit("--balancer needs HAProxy: scripts/services.sh haproxy")
        self.port = free_port()
        servers = "\n".join(f"    server daphne-{i} 127.0.0.1:{d.port}" for i, d in enumerate(daphnes))
        config = directory / "haproxy.cfg"
        config.write_text(CONFIG.format(port=self.port, maxconn=MAXCONN, servers=servers))
        self.log_path = directory / "haproxy.log"
        with self.log_path.open("wb") as out:
            self.process = subprocess.Popen(
                [haproxy, "-db", "-f", str(config)],
                stdout=out,
                stderr=subprocess.STDOUT,
                preexec_fn=_more_open_files,
            )
        self.pid = self.process.pid
