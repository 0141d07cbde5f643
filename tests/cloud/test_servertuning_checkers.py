"""daphne's two periodic passes, tuned to skip the connections with nothing due, against daphne's own.

Each test runs a real daphne Server (its Twisted reactor on asyncio, real sockets) twice: as daphne
ships it and with the two tunings. Its application answers ``/connections`` with how many
connections daphne still holds, so the tests see what the passes reap; they must see the same.
"""

from __future__ import annotations

import http.client
import json
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from websockets.client import ClientProtocol
from websockets.exceptions import ConnectionClosed
from websockets.frames import Opcode
from websockets.http11 import Response
from websockets.sync.client import connect
from websockets.uri import parse_uri

from ..conftest import wait_until

REPO = Path(__file__).resolve().parents[2]

SERVER = """
import asyncio, json, logging, sys
logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s %(message)s")
import daphne.server
from bridgeos_cloud import servertuning

port, tuned, lifetime, ping = int(sys.argv[1]), sys.argv[2] == "tuned", int(sys.argv[3]), int(sys.argv[4])
if tuned:
    servertuning.applications_reaped_when_they_end()
    servertuning.timeouts_checked_in_one_pass()

async def app(scope, receive, send):
    await receive()
    if scope["type"] == "http":
        if scope["path"] == "/boom":
            raise RuntimeError("boom inside the application")
        body = json.dumps({"connections": len(server.connections)}).encode()
        await send({"type": "http.response.start", "status": 200, "headers": [(b"content-type", b"application/json")]})
        await send({"type": "http.response.body", "body": body})
        return
    if scope["path"] == "/never-accepted":
        await asyncio.sleep(3600)
    await send({"type": "websocket.accept"})
    while (await receive())["type"] != "websocket.disconnect":
        pass
    if scope["path"] == "/stubborn":
        await asyncio.sleep(3600)  # ignores its close: daphne cancels it after the close timeout

server = daphne.server.Server(
    app,
    endpoints=[f"tcp:port={port}:interface=127.0.0.1"],
    websocket_timeout=lifetime,
    websocket_connect_timeout=2,
    ping_interval=ping,
    ping_timeout=30,
    application_close_timeout=1,
)
print("tuned" if type(server).application_checker.__module__ == "bridgeos_cloud.servertuning" else "daphne's own", flush=True)
server.run()
"""


class Daphne:
    def __init__(self, port: int, log: Path) -> None:
        self.port, self.log = port, log

    def connections(self) -> int:
        """Return how many connections daphne holds, this request's own among them."""
        connection = http.client.HTTPConnection("127.0.0.1", self.port, timeout=5)
        try:
            connection.request("GET", "/connections")
            return json.loads(connection.getresponse().read())["connections"]
        finally:
            connection.close()

    def logged(self, text: str) -> bool:
        return text in self.log.read_text(errors="replace")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@contextmanager
def start(tmp_path: Path, passes: str, lifetime: int = 86400, ping: int = 1) -> Iterator[Daphne]:
    script, log, port = tmp_path / "server.py", tmp_path / f"{passes}.log", free_port()
    script.write_text(SERVER)
    env = {**os.environ, "PYTHONPATH": f"{REPO}{os.pathsep}{os.environ.get('PYTHONPATH', '')}"}
    with log.open("w") as out:
        process = subprocess.Popen(
            [sys.executable, str(script), str(port), passes, str(lifetime), str(ping)],
            stdout=out,
            stderr=subprocess.STDOUT,
            env=env,
        )
    daphne = Daphne(port, log)
    try:
        wait_until(lambda: _answers(port), timeout=30, what="daphne to listen")
        assert daphne.logged("tuned" if passes == "tuned" else "daphne's own")
        yield daphne
    finally:
        process.terminate()
        process.wait(10)


def _answers(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
        return True
    except OSError:
        return False


@pytest.fixture(params=["daphne", "tuned"])
def daphne(request, tmp_path) -> Iterator[Daphne]:
    with start(tmp_path, request.param) as server:
        yield server


def test_closed_connections_are_forgotten(daphne):
    clients = [connect(f"ws://127.0.0.1:{daphne.port}/") for _ in range(20)]
    # Each upgrade's HTTP request is held too until a pass finds it closed: 41, then 21.
    wait_until(lambda: daphne.connections() == 21, timeout=5, what="daphne to forget the upgraded requests")
    for client in clients:
        client.close()
    wait_until(lambda: daphne.connections() == 1, timeout=5, what="daphne to forget the closed connections")


def test_an_applications_exception_is_logged_and_answered_and_its_connection_forgotten(daphne):
    connection = http.client.HTTPConnection("127.0.0.1", daphne.port, timeout=5)
    connection.request("GET", "/boom")
    assert connection.getresponse().status == 500
    connection.close()
    wait_until(
        lambda: daphne.logged("Exception inside application: boom inside the application"),
        timeout=5,
        what="the exception logged",
    )
    wait_until(lambda: daphne.connections() == 1, timeout=5)


def test_an_application_that_ignores_its_close_is_cancelled_after_the_close_timeout(daphne):
    connect(f"ws://127.0.0.1:{daphne.port}/stubborn").close()
    wait_until(
        lambda: daphne.logged("took too long to shut down and was killed"), timeout=6, what="the cancellation logged"
    )
    wait_until(lambda: daphne.connections() == 1, timeout=5)


def raw_upgrade(port: int, path: str) -> tuple[socket.socket, ClientProtocol]:
    ws = ClientProtocol(parse_uri(f"ws://127.0.0.1:{port}{path}"))
    sock = socket.create_connection(("127.0.0.1", port), timeout=10)
    ws.send_request(ws.connect())
    sock.sendall(b"".join(ws.data_to_send()))
    return sock, ws


def first_events(sock: socket.socket, ws: ClientProtocol, count: int) -> list:
    events: list = []
    while len(events) < count:
        data = sock.recv(65536)
        assert data, f"daphne closed the connection after {events}"
        ws.receive_data(data)
        events.extend(ws.events_received())
    return events


def test_a_silent_connection_is_pinged_and_one_never_accepted_is_refused(daphne):
    sock, ws = raw_upgrade(daphne.port, "/")
    with sock:
        started = time.monotonic()
        handshake, frame = first_events(sock, ws, 2)
        assert isinstance(handshake, Response) and handshake.status_code == 101
        assert frame.opcode is Opcode.PING, frame  # ping interval 1 s, the pass every 2 s
        assert time.monotonic() - started < 5
    sock, _ = raw_upgrade(daphne.port, "/never-accepted")
    with sock:
        started = time.monotonic()
        refusal = b""
        while chunk := sock.recv(65536):  # a 403 without a length: read to the end
            refusal += chunk
        assert refusal.startswith(b"HTTP/1.1 403 "), refusal
        assert 1.5 < time.monotonic() - started < 5  # the connect timeout is 2 s, the pass every 2 s


@pytest.mark.parametrize("passes", ["daphne", "tuned"])
def test_a_connection_past_its_lifetime_is_closed(tmp_path, passes):
    # Pinged every 10 s, so only its lifetime of 3 s can close it.
    with start(tmp_path, passes, lifetime=3, ping=10) as daphne:
        with connect(f"ws://127.0.0.1:{daphne.port}/") as client:
            started = time.monotonic()
            with pytest.raises(ConnectionClosed):
                client.recv(timeout=10)
            assert 1 < time.monotonic() - started < 7
