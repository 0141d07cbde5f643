"""tenk.py's HAProxy: real HAProxy in front of two servers, and a fleet too large for it refused."""

from __future__ import annotations

import shutil
import subprocess
import sys
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from types import SimpleNamespace

import httpx
import pytest

from benchmarks._balancer import Balancer, balancer_capacity

ROOT = Path(__file__).resolve().parent.parent.parent

pytestmark = pytest.mark.skipif(
    not shutil.which("haproxy"), reason="HAProxy is not installed (scripts/services.sh haproxy)"
)


def server(name: str) -> ThreadingHTTPServer:
    """An HTTP server on a free port that answers every GET with its name, holding the connection open."""

    class Answer(BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def do_GET(self) -> None:
            body = name.encode()
            self.send_response(200)
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Answer)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    return httpd


def test_held_connections_are_spread_over_the_servers_fewest_first(tmp_path):
    servers = [server("one"), server("two")]
    balancer = Balancer([SimpleNamespace(port=s.server_address[1]) for s in servers], tmp_path)
    clients = [httpx.Client(base_url=f"http://127.0.0.1:{balancer.port}") for _ in range(4)]
    try:
        balancer.wait()
        # Each client keeps its connection, as a robot keeps its WebSocket: the next goes to the other server.
        answers = [client.get("/").raise_for_status().text for client in clients]
        assert sorted(answers) == ["one", "one", "two", "two"]
        assert balancer.cpu_seconds() >= 0
    finally:
        for client in clients:
            client.close()
        balancer.stop()
        for s in servers:
            s.shutdown()
    assert balancer.process.returncode is not None


def test_a_fleet_larger_than_haproxy_may_hold_is_refused_saying_why():
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / "tenk.py"), "--balancer", "--robots", str(balancer_capacity() + 1)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2
    assert f"HAProxy holds at most {balancer_capacity()} connections" in done.stderr
    assert "created" not in done.stderr  # refused before any robot was made
