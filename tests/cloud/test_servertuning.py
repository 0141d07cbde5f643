"""daphne's tunings as a robot and an operator see them: its access log, and the writes of a robot's login."""

from __future__ import annotations

import http.client
import json
import signal
import socket
import struct
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from django.contrib.auth import get_user_model
from websockets.client import ClientProtocol
from websockets.frames import Frame, Opcode
from websockets.http11 import Response
from websockets.uri import parse_uri

from bridgeos_cloud.servertuning import ACCESS_LOG_FLUSH_S, CLOSE_HANDSHAKE_TIMEOUT_S, call_and_log_failures, unmask
from monitoring.models import Metric
from robots.services import create_robot

from ..conftest import another_daphne, wait_until

pytestmark = pytest.mark.django_db(transaction=True)

REQUESTS = 300


def get_health(connection: http.client.HTTPConnection, marker: str) -> None:
    connection.request("GET", f"/api/health?{marker}")
    response = connection.getresponse()
    response.read()
    assert response.status == 200


def lines_with(log: Path, marker: str) -> int:
    return log.read_text(errors="replace").count(f"GET /api/health?{marker}")


def test_access_lines_are_written_in_blocks_and_reach_the_log_within_the_flush_period(tmp_path):
    log = tmp_path / "daphne.log"
    with another_daphne(log) as (server, _process):
        connection = http.client.HTTPConnection(server.host, server.port, timeout=10)
        get_health(connection, "warm")
        wait_until(lambda: lines_with(log, "warm") == 1, timeout=5, what="the warm-up request's line")
        # The log's size after each request: written a line at a time, it grows with every one.
        sizes = set()
        for _ in range(REQUESTS):
            get_health(connection, "block")
            sizes.add(log.stat().st_size)
        assert len(sizes) < REQUESTS / 10, f"the log grew {len(sizes)} times during {REQUESTS} requests"
        wait_until(
            lambda: lines_with(log, "block") == REQUESTS,
            timeout=ACCESS_LOG_FLUSH_S + 2,
            what=f"all {REQUESTS} access lines in the log",
        )
        connection.close()


def test_the_last_access_lines_are_written_when_daphne_stops(tmp_path):
    log = tmp_path / "daphne.log"
    with another_daphne(log) as (server, process):
        connection = http.client.HTTPConnection(server.host, server.port, timeout=10)
        for _ in range(50):
            get_health(connection, "last")
        connection.close()
        process.send_signal(signal.SIGTERM)
        process.wait(timeout=30)
    assert lines_with(log, "last") == 50


def test_daphne_serves_on_uvloop_and_still_stops_gracefully(tmp_path):
    log = tmp_path / "daphne.log"
    with another_daphne(log) as (server, process):
        # The loop is chosen before daphne creates it (bridgeos_cloud/serve.py): its C module is loaded.
        assert "uvloop/loop." in Path(f"/proc/{process.pid}/maps").read_text()
        connection = http.client.HTTPConnection(server.host, server.port, timeout=10)
        get_health(connection, "uvloop")
        connection.close()
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=30) == 0
    # Twisted's shutdown ran on it: the loop's objects were closed in order.
    assert "bridgeos_cloud.loopowned: closed" in log.read_text()


# Where Linux's struct tcp_info keeps tcpi_data_segs_in (segments that carried data), stable since 4.6.
TCP_INFO_DATA_SEGS_IN = 152
LOGIN_FRAMES = ["authentication_success", "connection_established", "robot_config"]


def data_segments_in(sock: socket.socket) -> int:
    return struct.unpack_from("I", sock.getsockopt(socket.IPPROTO_TCP, socket.TCP_INFO, 256), TCP_INFO_DATA_SEGS_IN)[0]


def frames_until(sock: socket.socket, ws: ClientProtocol, last_event: str, timeout: float = 15.0) -> list[str]:
    """Read from the socket until ``last_event`` arrives; return the events of the frames read."""
    events: list[str] = []
    deadline = time.monotonic() + timeout
    while last_event not in events:
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        data = sock.recv(65536)
        assert data, f"daphne closed the connection after {events}"
        ws.receive_data(data)
        for received in ws.events_received():
            if isinstance(received, Response):
                events.append("handshake")
            else:
                events.append(json.loads(received.data)["event"])
    return events


def test_a_robots_login_frames_reach_it_together_in_one_segment(daphne_server):
    owner = get_user_model().objects.create_user("gathered-owner")
    _, token = create_robot("gathered-bot", owner)
    ws = ClientProtocol(parse_uri(f"{daphne_server.ws_url}/ws/robot/"))
    with socket.create_connection((daphne_server.host, daphne_server.port), timeout=15) as sock:
        ws.send_request(ws.connect())
        sock.sendall(b"".join(ws.data_to_send()))
        assert frames_until(sock, ws, "handshake") == ["handshake"]
        before = data_segments_in(sock)
        credentials = {"robot": "gathered-bot", "token": token}
        ws.send_text(json.dumps({"event": "authentication_robot", "id": "login-1", "data": credentials}).encode())
        sock.sendall(b"".join(ws.data_to_send()))
        events = frames_until(sock, ws, LOGIN_FRAMES[-1])
        segments = data_segments_in(sock) - before
    assert events == LOGIN_FRAMES
    # Sent one by one (TCP_NODELAY, as autobahn sets), each frame was a segment of its own: three.
    assert segments == 1, f"the login's {len(events)} frames came in {segments} segments"


def read_frames(sock: socket.socket, ws: ClientProtocol, done: Callable[[list[Frame]], bool]) -> list[Frame]:
    """Read frames until ``done`` says they are all there; return them."""
    frames: list[Frame] = []
    deadline = time.monotonic() + 15
    while not done(frames):
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        data = sock.recv(65536)
        assert data, f"daphne closed the connection after {frames}"
        ws.receive_data(data)
        frames.extend(ws.events_received())
    return frames


def pongs(frames: list[Frame]) -> list[bytes]:
    return [bytes(frame.data) for frame in frames if frame.opcode is Opcode.PONG]


def opened(daphne_server) -> tuple[socket.socket, ClientProtocol]:
    ws = ClientProtocol(parse_uri(f"{daphne_server.ws_url}/ws/robot/"))
    sock = socket.create_connection((daphne_server.host, daphne_server.port), timeout=15)
    ws.send_request(ws.connect())
    sock.sendall(b"".join(ws.data_to_send()))
    assert frames_until(sock, ws, "handshake") == ["handshake"]
    return sock, ws


@pytest.mark.parametrize("payload", [b"", b"beat-1", bytes(range(125))])
def test_a_lone_ping_gets_its_own_payload_back(daphne_server, payload):
    sock, ws = opened(daphne_server)
    with sock:
        for _ in range(3):
            ws.send_ping(payload)
            sock.sendall(b"".join(ws.data_to_send()))  # one ping, one segment: answered directly
            assert pongs(read_frames(sock, ws, lambda frames: bool(frames))) == [payload]


def test_a_ping_sent_together_with_a_frame_is_answered_and_the_frame_handled(daphne_server):
    owner = get_user_model().objects.create_user("ping-owner")
    _, token = create_robot("ping-bot", owner)
    sock, ws = opened(daphne_server)
    with sock:
        credentials = {"robot": "ping-bot", "token": token}
        ws.send_ping(b"first")
        ws.send_text(json.dumps({"event": "authentication_robot", "id": "login-1", "data": credentials}).encode())
        ws.send_ping(b"second")
        # Two pings and a login in one segment: not a lone ping, so the general parser takes all three.
        sock.sendall(b"".join(ws.data_to_send()))

        def texts(frames: list[Frame]) -> list[str]:
            return [json.loads(frame.data)["event"] for frame in frames if frame.opcode is Opcode.TEXT]

        frames = read_frames(sock, ws, lambda frames: len(pongs(frames)) == 2 and "robot_config" in texts(frames))
    assert pongs(frames) == [b"first", b"second"]
    assert texts(frames) == LOGIN_FRAMES


@pytest.mark.parametrize("size", [1, 3, 4, 5, 125, 126, 1000, 65535])
def test_unmasking_is_the_rfc_xor_of_every_byte_with_the_key(size):
    payload, mask = bytes((7 * i + 3) % 256 for i in range(size)), b"\x9a\x01\xff\x42"
    assert unmask(payload, mask) == bytes(byte ^ mask[i % 4] for i, byte in enumerate(payload))


def texts_of(frames: list[Frame]) -> list[dict]:
    return [json.loads(frame.data) for frame in frames if frame.opcode is Opcode.TEXT]


def logged_in(daphne_server, name: str) -> tuple[socket.socket, ClientProtocol]:
    owner = get_user_model().objects.create_user(f"{name}-owner")
    _, token = create_robot(name, owner)
    sock, ws = opened(daphne_server)
    # A lone text frame in one segment: read directly.
    ws.send_text(
        json.dumps({"event": "authentication_robot", "id": "login-1", "data": {"robot": name, "token": token}}).encode()
    )
    sock.sendall(b"".join(ws.data_to_send()))
    frames = read_frames(sock, ws, lambda frames: "robot_config" in [t["event"] for t in texts_of(frames)])
    assert [text["event"] for text in texts_of(frames)] == LOGIN_FRAMES
    return sock, ws


def test_lone_text_frames_of_each_length_encoding_reach_the_robot_consumer_whole(daphne_server):
    sock, ws = logged_in(daphne_server, "direct-text-bot")
    with sock:
        now = time.time()
        for count in (1, 40):  # a 7-bit length, then a 16-bit one
            points = [{"name": f"m{i}", "value": i + 0.5, "ts": now} for i in range(count)]
            frame = {"event": "metrics", "id": f"metrics-{count}", "data": {"metrics": points}, "ts": now}
            ws.send_text(json.dumps(frame).encode())
            sock.sendall(b"".join(ws.data_to_send()))
            (answer,) = texts_of(read_frames(sock, ws, lambda frames: bool(texts_of(frames))))
            assert (answer["event"], answer["reply_to"]) == ("ack", f"metrics-{count}")
        # Text beyond ASCII arrives as the robot wrote it: the refusal names the event it was sent.
        ws.send_text(json.dumps({"event": "größe-✓", "id": "odd-1", "data": {}}, ensure_ascii=False).encode())
        sock.sendall(b"".join(ws.data_to_send()))
        (refusal,) = texts_of(read_frames(sock, ws, lambda frames: bool(texts_of(frames))))
    assert refusal["event"] == "error_message" and "größe-✓" in refusal["data"]["message"]
    stored = Metric.objects.filter(robot_id="direct-text-bot")
    assert stored.count() == 41 and set(stored.values_list("name", flat=True)) == {f"m{i}" for i in range(40)}


def test_a_text_frame_split_over_segments_is_read_the_general_way(daphne_server):
    sock, ws = logged_in(daphne_server, "split-text-bot")
    with sock:
        frame = {
            "event": "metrics",
            "id": "split-1",
            "data": {"metrics": [{"name": "m", "value": 1.5, "ts": time.time()}]},
        }
        ws.send_text(json.dumps(frame).encode())
        data = b"".join(ws.data_to_send())
        sock.sendall(data[:9])
        time.sleep(0.2)
        sock.sendall(data[9:])
        (answer,) = texts_of(read_frames(sock, ws, lambda frames: bool(texts_of(frames))))
    assert (answer["event"], answer["reply_to"]) == ("ack", "split-1")


def how_it_ends(sock: socket.socket, ws: ClientProtocol) -> str:
    """Read until daphne ends the connection; return how: its close code, or that it dropped the socket."""
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        sock.settimeout(max(0.01, deadline - time.monotonic()))
        try:
            data = sock.recv(65536)
        except ConnectionResetError:
            return "dropped"
        if not data:
            return "dropped"
        ws.receive_data(data)
        for frame in ws.events_received():
            assert frame.opcode is not Opcode.TEXT, f"a bad frame was answered: {frame.data!r}"
            if frame.opcode is Opcode.CLOSE:
                return f"closed {struct.unpack('!H', bytes(frame.data[:2]))[0]}"
    raise AssertionError("daphne kept the connection open")


def bad_frame_endings(daphne_server, name: str, frame: bytes) -> list[str]:
    """Send a bad frame in one segment (a candidate for the direct path) and split (the general one)."""
    endings = []
    for split in (False, True):
        sock, ws = logged_in(daphne_server, f"{name}-{int(split)}")
        with sock:
            if split:
                sock.sendall(frame[:3])
                time.sleep(0.2)
                sock.sendall(frame[3:])
            else:
                sock.sendall(frame)
            endings.append(how_it_ends(sock, ws))
    return endings


def test_a_lone_text_frame_of_invalid_utf8_ends_the_connection_as_autobahn_does(daphne_server):
    payload, mask = b'{"event": "metrics", "id": "\xff\xfe"}', b"\x01\x02\x03\x04"
    frame = bytes((0x81, 0x80 | len(payload))) + mask + unmask(payload, mask)
    one_segment, split = bad_frame_endings(daphne_server, "bad-utf8", frame)
    assert one_segment == split


def test_a_lone_text_frame_whose_length_is_not_minimally_encoded_ends_the_connection_as_autobahn_does(daphne_server):
    payload, mask = b'{"event":"x"}', b"\x01\x02\x03\x04"
    # A 13-byte payload announced in the 16-bit form: RFC 6455 allows only the shortest form.
    frame = bytes((0x81, 0x80 | 126)) + len(payload).to_bytes(2, "big") + mask + unmask(payload, mask)
    one_segment, split = bad_frame_endings(daphne_server, "long-length", frame)
    assert one_segment == split


def test_a_client_slow_to_answer_daphnes_close_still_reads_its_refusal_and_sends_its_reply(daphne_server):
    sock, ws = opened(daphne_server)
    with sock:
        ws.send_text(b"[{}]")  # not a frame of the protocol: refused, and the connection closed
        sock.sendall(b"".join(ws.data_to_send()))
        # Longer than autobahn's own 1 s, after which it reset the connection: the reply below then
        # failed, and websockets' sync client dropped the refusal it had read (a starved fuzz test's
        # client did). A robot on a slow link, or a client thread the machine starves, is this slow.
        time.sleep(2.0)
        frames = read_frames(sock, ws, lambda frames: any(frame.opcode is Opcode.CLOSE for frame in frames))
        sock.sendall(b"".join(ws.data_to_send()))  # the client's close reply: not refused by a reset
        # The handshake done, autobahn drops the connection (a reset, as it does for every server close).
        sock.settimeout(CLOSE_HANDSHAKE_TIMEOUT_S)
        with pytest.raises(ConnectionResetError):
            sock.recv(65536)
    (refusal,) = texts_of(frames)
    assert refusal["event"] == "authentication_failure"


# Where a Twisted client (roslibpy) forwards Twisted's log to Python's, the failure is an ERROR line.
@pytest.mark.log_errors(r"ZeroDivisionError")
def test_a_ready_sockets_handler_returns_as_before_and_its_failure_is_logged_with_the_connections_prefix():
    from twisted.python import log

    class Connection:
        def logPrefix(self) -> str:
            return "WebSocketProtocol,7,127.0.0.1"

    events: list[dict] = []
    log.addObserver(events.append)
    try:
        assert call_and_log_failures(Connection(), lambda a, b=0: a + b, 1, b=2) == 3
        assert call_and_log_failures(Connection(), lambda: 1 / 0) is None
    finally:
        log.removeObserver(events.append)
    (failure,) = [event for event in events if event.get("isError")]
    assert failure["system"] == "WebSocketProtocol,7,127.0.0.1"
    assert failure["failure"].check(ZeroDivisionError)
