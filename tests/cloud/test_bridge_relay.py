"""rosbridge through the cloud: real clients (roslibpy, roslib from npm) → daphne → a real agent → real ROS 1.

A daphne of this module's own (small per-client caps, so flow control shows in seconds), a
RobotController connected to it over a real socket, a private rosmaster with rospy nodes, and the
clients a robot's owner would use, authenticated with an API token or a single-use ticket.
"""

from __future__ import annotations

import base64
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import time
from collections import Counter
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

import httpx
import pytest
import roslibpy
from django.utils import timezone
from websockets.exceptions import ConnectionClosed, InvalidStatus
from websockets.sync.client import ClientConnection, connect

from bridgeos_agent.controller import AgentSettings, RobotController
from robots.models import BridgeTicket, Robot
from robots.services import create_robot, issue_api_token
from tests.agent.foxgloveclient import FoxgloveClient, node_client_ready
from tests.agent.roshelpers import HOST_PYTHON, Nodes, private_rosmaster
from tests.conftest import ROOT, LoopThread, Server, another_daphne, wait_until

pytestmark = [pytest.mark.ros, pytest.mark.django_db(transaction=True), pytest.mark.timeout(120)]

BYTES_PER_S = 40_000  # each client's cap in this cloud
MAX_FRAME = 64 * 1024  # the largest client frame this cloud passes on
FRAMES_PER_S = 100  # how often a client may send, with bursts of 200
JS_DIR = ROOT / "tests" / "js" / "roslib"


@pytest.fixture(scope="module")
def cloud(django_db_setup, django_db_blocker, tmp_path_factory) -> Iterator[Server]:
    log = tmp_path_factory.mktemp("bridge-cloud") / "daphne.log"
    with another_daphne(
        log,
        BRIDGEOS_BRIDGE_CLIENT_BYTES_PER_S=str(BYTES_PER_S),
        BRIDGEOS_BRIDGE_MAX_FRAME_BYTES=str(MAX_FRAME),
        BRIDGEOS_BRIDGE_CLIENT_FRAMES_PER_S=str(FRAMES_PER_S),
        BRIDGEOS_BRIDGE_CLIENT_FRAME_BURST=str(2 * FRAMES_PER_S),
    ) as (server, _):
        yield server


@pytest.fixture(scope="module")
def ros(tmp_path_factory) -> Iterator[tuple[str, Nodes]]:
    if not (Path(HOST_PYTHON).exists() and Path("/usr/bin/rosmaster").exists()):
        pytest.skip("Debian's ROS 1 (rospy, rosmaster) is not installed")
    home = tmp_path_factory.mktemp("bridge-ros")
    with private_rosmaster(home) as master:
        nodes = Nodes(master, home)
        nodes.run("talker", "talker", "--topic", "/chatter", "--rate", "20", "--tag", "robot")
        # ~1 kB at 200 Hz: five times what one client may receive here.
        nodes.run("fast", "talker", "--topic", "/fast", "--rate", "200", "--size", "1000", "--tag", "fast")
        nodes.run("listener", "listener", "--topic", "/from_client")
        nodes.run("server", "server", "--service", "/trigger", "--tag", "robot")
        nodes.tool("/usr/bin/rosparam", "set", "/robot/gain", "2.5")
        try:
            wait_until(lambda: "ready" in nodes.lines("server") and "ready" in nodes.lines("listener"), what="nodes")
            yield master, nodes
        finally:
            nodes.kill_all()


@dataclass
class Bot:
    id: str
    api_token: str
    controller: RobotController
    loop: LoopThread

    def engine(self) -> Any:
        return self.controller.bridges.engines.get("rosbridge")


def make_robot(robot_id: str) -> tuple[str, str]:
    from django.contrib.auth import get_user_model

    owner = get_user_model().objects.create_user(f"owner-{robot_id}")
    _, token = create_robot(robot_id, owner)
    return token, issue_api_token(owner)[0]


@pytest.fixture
def robot(cloud: Server, ros: tuple[str, Nodes], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[Bot]:
    master, _ = ros
    monkeypatch.setenv("ROS_MASTER_URI", master)
    token, api_token = make_robot("br-1")
    settings = AgentSettings(
        master=cloud.ws_url,
        robot="br-1",
        token=token,
        data_dir=tmp_path / "agent",
        simulate=True,
        reconnect_initial=0.2,
    )
    loop = LoopThread()
    controller = loop.call(lambda: RobotController(settings, plugins={}))
    # Topics left by the last client go from the graph after 0.3 s (5 s by default), so tests see it.
    controller.bridges.engine_options = {"rosbridge": {"linger_s": 0.3}}
    running = loop.start(controller.run())
    try:
        wait_until(lambda: Robot.objects.filter(id="br-1", connected=True).exists(), what="the robot connected")
        yield Bot("br-1", api_token, controller, loop)
    finally:
        loop.loop.call_soon_threadsafe(controller.stop)
        running.result(30)
        loop.stop()
        wait_until(lambda: not Robot.objects.filter(connected=True).exists(), what="the robot recorded offline")


def url(cloud: Server, robot_id: str, kind: str = "rosbridge") -> str:
    return f"{cloud.ws_url}/ws/{kind}/{robot_id}/"


def token_client(cloud: Server, bot: Bot) -> roslibpy.Ros:
    ros = roslibpy.Ros(url(cloud, bot.id), headers={"Authorization": f"Token {bot.api_token}"})
    ros.run(timeout=10)
    return ros


def ticket(cloud: Server, robot_id: str, api_token: str) -> dict[str, Any]:
    answer = httpx.post(
        f"{cloud.url}/api/robot/{robot_id}/bridge-ticket", headers={"Authorization": f"Token {api_token}"}
    )
    assert answer.status_code == 200, answer.text
    return answer.json()


def raw(address: str, **kw: Any) -> ClientConnection:
    return connect(address, max_size=None, open_timeout=10, **kw)


def stalled_client(cloud: Server, path: str, token: str, text: str) -> socket.socket:
    """Open a WebSocket by hand, send one text frame, and never read again (a viewer whose tab froze)."""
    sock = socket.create_connection((cloud.host, cloud.port), timeout=10)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(
        (
            f"GET {path} HTTP/1.1\r\nHost: {cloud.host}:{cloud.port}\r\nUpgrade: websocket\r\n"
            f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
            f"Authorization: Token {token}\r\n\r\n"
        ).encode()
    )
    answer = b""
    while b"\r\n\r\n" not in answer:
        answer += sock.recv(1)
    assert answer.startswith(b"HTTP/1.1 101"), answer
    payload, mask = text.encode(), os.urandom(4)
    assert len(payload) < 126
    masked = bytes(byte ^ mask[i % 4] for i, byte in enumerate(payload))
    sock.sendall(bytes([0x81, 0x80 | len(payload)]) + mask + masked)
    return sock


def counters(cloud: Server, **labels: str) -> Counter[str]:
    """Return the cloud's bridge counters on /metrics, summed over the series matching ``labels``."""
    found: Counter[str] = Counter()
    for line in httpx.get(f"{cloud.url}/metrics", timeout=10).text.splitlines():
        match = re.match(r"^(bridgeos_bridge_\w+_total)(?:\{([^}]*)\})? (\S+)$", line)
        if match:
            series = dict(re.findall(r'(\w+)="([^"]*)"', match.group(2) or ""))
            if all(series.get(key) == value for key, value in labels.items()):
                found[match.group(1)] += float(match.group(3))
    return found


def next_op(websocket: ClientConnection, op: str, timeout: float = 10) -> dict[str, Any]:
    deadline = time.monotonic() + timeout
    while True:
        message = json.loads(websocket.recv(timeout=max(0.1, deadline - time.monotonic())))
        if message.get("op") == op:
            return message


# ---------------------------------------------------------------------- roslibpy through the cloud


def test_roslibpy_reaches_the_robots_topics_services_rosapi_and_params_through_the_cloud(cloud, robot, ros) -> None:
    _, nodes = ros
    client = token_client(cloud, robot)
    try:
        heard: list[dict[str, Any]] = []
        chatter = roslibpy.Topic(client, "/chatter", "std_msgs/String")
        chatter.subscribe(heard.append)
        wait_until(lambda: len(heard) >= 5, what="the robot's talker through the cloud")
        assert all(message["data"].startswith("robot ") for message in heard)
        assert "/chatter" in robot.engine().subscribed_topics()  # subscribed on the robot while listened to

        said = roslibpy.Topic(client, "/from_client", "std_msgs/String")
        said.advertise()

        def listener_heard() -> bool:
            said.publish(roslibpy.Message({"data": f"client 1 {time.time():.6f}"}))
            return any(line.startswith("client ") for line in nodes.lines("listener"))

        wait_until(listener_heard, what="the robot's listener to hear the client")

        trigger = roslibpy.Service(client, "/trigger", "std_srvs/Trigger")
        assert trigger.call(roslibpy.ServiceRequest({}), timeout=15) == {"success": True, "message": "robot"}
        assert "/chatter" in client.get_topics()
        assert client.get_topic_type("/chatter") == "std_msgs/String"
        assert "/trigger" in client.get_services()
        assert roslibpy.Param(client, "/robot/gain").get(timeout=10) == 2.5
        roslibpy.Param(client, "/robot/gain").set(4.0, timeout=10)
        assert roslibpy.Param(client, "/robot/gain").get(timeout=10) == 4.0

        chatter.unsubscribe()
        wait_until(lambda: "/chatter" not in robot.engine().subscribed_topics(), what="the robot to unsubscribe")
    finally:
        # Closed for good before the robot's fixture stops it: the cloud tells a client still
        # there that the robot went offline (a rosbridge status), which roslibpy logs as an error.
        client.close()
        wait_until(lambda: not client.is_connected, what="the client to close")


def test_a_stalled_viewer_slows_neither_the_robot_nor_a_live_viewer(cloud, robot) -> None:
    # This client never reads: its socket buffers fill, then daphne's, then its session's queues on the robot.
    subscribe = json.dumps({"op": "subscribe", "topic": "/fast", "queue_length": 10})
    stalled = stalled_client(cloud, f"/ws/rosbridge/{robot.id}/", robot.api_token, subscribe)
    live = token_client(cloud, robot)
    try:
        fast: list[dict[str, Any]] = []
        chatter: list[dict[str, Any]] = []
        throttled: list[dict[str, Any]] = []
        roslibpy.Topic(live, "/fast", "std_msgs/String").subscribe(fast.append)
        roslibpy.Topic(live, "/chatter", "std_msgs/String").subscribe(chatter.append)
        other = token_client(cloud, robot)
        roslibpy.Topic(other, "/chatter", "std_msgs/String", throttle_rate=1000).subscribe(throttled.append)
        wait_until(lambda: fast and chatter and throttled, what="the live viewers' first messages")
        start = (len(fast), len(chatter), len(throttled))
        time.sleep(3.0)
        got_fast, got_chatter, got_throttled = (
            len(fast) - start[0],
            len(chatter) - start[1],
            len(throttled) - start[2],
        )
        other.close()
        # The live viewer gets /chatter in full (every message the 20 Hz talker published: no gap in its
        # sequence numbers; a loaded machine may slow the talker itself) beside /fast, which its byte cap
        # thins to ~40 kB/s (1 kB messages: 3 s at the cap, plus at most one second's burst).
        seqs = [int(m["data"].split()[1]) for m in chatter[start[1] - 1 :]]
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), seqs
        assert got_chatter >= 30, got_chatter
        assert 40 <= got_fast <= (3 + 1) * BYTES_PER_S / 1000, got_fast
        assert 2 <= got_throttled <= 4, got_throttled  # throttle_rate 1000 ms
        # The stalled viewer lost its own oldest messages, counted on the robot.
        sessions = list(robot.controller.bridges.sessions.values())
        drops = [s.engine_session.stats().get("/fast", {}).get("dropped", 0) for s in sessions if s.engine_session]
        assert max(drops) > 100, drops
        # And on the cloud's /metrics, told by the robot with the frames it still sends.
        where = {"kind": "rosbridge", "where": "robot_queue"}
        wait_until(lambda: counters(cloud, **where)["bridgeos_bridge_drops_total"] > 100, what="drops on /metrics")
    finally:
        live.close()
        stalled.close()


def test_a_client_on_another_cloud_process_reaches_the_robot_through_the_channel_layer(cloud, robot, tmp_path) -> None:
    with another_daphne(tmp_path / "second.log") as (second, _):
        address = f"{second.ws_url}/ws/rosbridge/{robot.id}/"
        with raw(address, additional_headers={"Authorization": f"Token {robot.api_token}"}) as websocket:
            websocket.send(json.dumps({"op": "subscribe", "topic": "/chatter"}))
            assert next_op(websocket, "publish")["msg"]["data"].startswith("robot ")
            websocket.send(json.dumps({"op": "call_service", "id": "x", "service": "/trigger"}))
            assert next_op(websocket, "service_response")["values"]["message"] == "robot"


# ---------------------------------------------------------------------- who gets in


def refused(address: str, **kw: Any) -> int:
    with pytest.raises(InvalidStatus) as caught:
        raw(address, **kw).close()
    return caught.value.response.status_code


def test_only_the_owner_gets_in_and_a_ticket_serves_once(cloud, robot) -> None:
    _, stranger = make_robot("br-other")
    assert refused(url(cloud, robot.id), additional_headers={"Authorization": f"Token {stranger}"}) == 403
    assert refused(url(cloud, "br-nobody"), additional_headers={"Authorization": f"Token {robot.api_token}"}) == 403
    assert refused(url(cloud, robot.id)) == 403
    assert refused(url(cloud, robot.id) + "?ticket=bbt_forged") == 403
    # Another user cannot get a ticket for this robot either: to them it does not exist.
    answer = httpx.post(
        f"{cloud.url}/api/robot/{robot.id}/bridge-ticket", headers={"Authorization": f"Token {stranger}"}
    )
    assert answer.status_code == 404

    issued = ticket(cloud, robot.id, robot.api_token)
    assert issued["rosbridge_url"] == url(cloud, robot.id) + "?ticket=" + issued["ticket"]
    assert issued["foxglove_url"] == url(cloud, robot.id, "foxglove") + "?ticket=" + issued["ticket"]
    assert issued["ticket"] not in str(list(BridgeTicket.objects.values()))  # kept hashed
    assert refused(url(cloud, "br-other") + "?ticket=" + issued["ticket"]) == 403  # for this robot only
    with raw(issued["rosbridge_url"]) as websocket:
        websocket.send(json.dumps({"op": "call_service", "id": "t", "service": "/trigger"}))
        assert next_op(websocket, "service_response")["values"] == {"success": True, "message": "robot"}
    assert refused(issued["rosbridge_url"]) == 403  # spent

    late = ticket(cloud, robot.id, robot.api_token)
    BridgeTicket.objects.update(expires_at=timezone.now() - timedelta(seconds=1))
    assert refused(late["rosbridge_url"]) == 403


def test_roslib_from_npm_subscribes_through_the_cloud_with_a_ticket(cloud, robot) -> None:
    node = shutil.which("node")
    if node is None:
        pytest.skip("node is not installed (scripts/services.sh node)")
    if not (JS_DIR / "node_modules" / "roslib").exists():
        subprocess.run(["npm", "ci", "--no-audit", "--no-fund"], cwd=JS_DIR, check=True, capture_output=True)
    address = ticket(cloud, robot.id, robot.api_token)["rosbridge_url"]
    done = subprocess.run(
        [node, "subscribe.mjs", address, "/chatter", "std_msgs/String", "3"],
        cwd=JS_DIR,
        capture_output=True,
        text=True,
        timeout=60,
    )
    events = [json.loads(line) for line in done.stdout.splitlines() if line.startswith("{")]
    messages = [event["message"] for event in events if event["event"] == "message"]
    assert done.returncode == 0, done.stdout + done.stderr
    assert len(messages) == 3 and all(message["data"].startswith("robot ") for message in messages)


# ---------------------------------------------------------------------- offline, Foxglove, bad input


def test_an_offline_robot_says_so_and_closes(cloud, robot) -> None:
    _, api_token = make_robot("br-off")
    with raw(url(cloud, "br-off"), additional_headers={"Authorization": f"Token {api_token}"}) as websocket:
        status = next_op(websocket, "status")
        assert status["level"] == "error" and "br-off is offline" in status["msg"]
        with pytest.raises(ConnectionClosed) as caught:
            websocket.recv(timeout=5)
    assert caught.value.rcvd.code == 4010

    # Connected when the client came, gone while it is on: the client is told and closed.
    with raw(url(cloud, robot.id), additional_headers={"Authorization": f"Token {robot.api_token}"}) as websocket:
        websocket.send(json.dumps({"op": "subscribe", "topic": "/chatter"}))
        next_op(websocket, "publish")
        robot.loop.loop.call_soon_threadsafe(robot.controller.stop)
        status = next_op(websocket, "status")
        assert "went offline" in status["msg"]
        with pytest.raises(ConnectionClosed) as caught:
            while True:
                websocket.recv(timeout=10)
    assert caught.value.rcvd.code == 4010


def test_the_foxglove_door_takes_either_subprotocol_and_speaks_foxglove(cloud, robot) -> None:
    headers = {"Authorization": f"Token {robot.api_token}"}
    assert refused(url(cloud, robot.id, "foxglove"), additional_headers=headers) == 403  # no subprotocol offered
    for subprotocol in ("foxglove.websocket.v1", "foxglove.sdk.v1"):
        with raw(url(cloud, robot.id, "foxglove"), additional_headers=headers, subprotocols=[subprotocol]) as ws:
            assert ws.subprotocol == subprotocol
            assert json.loads(ws.recv(timeout=10))["op"] == "serverInfo"


def test_foxgloves_own_client_subscribes_through_the_cloud_with_a_ticket(cloud, robot) -> None:
    if not node_client_ready():
        pytest.skip("node or tests/js/foxglove/node_modules is missing: run scripts/services.sh node")
    client = FoxgloveClient(ticket(cloud, robot.id, robot.api_token)["foxglove_url"])
    try:
        assert client.wait("serverInfo")["info"]["name"]
        channel = client.channel("/chatter")
        assert (channel["encoding"], channel["schemaName"], channel["schemaEncoding"]) == (
            "ros1",
            "std_msgs/String",
            "ros1msg",
        )
        client.command("subscribe", topic="/chatter")
        subscription = client.wait("subscribed")["subscriptionId"]
        for _ in range(3):
            data = base64.b64decode(client.wait("message", lambda e: e["subscriptionId"] == subscription)["data"])
            (length,) = struct.unpack_from("<I", data)  # ROS 1 std_msgs/String: a length, then the bytes
            assert data[4 : 4 + length].decode().startswith("robot ")
    finally:
        client.close()


def test_bad_input_gets_a_status_naming_it_and_the_connection_keeps_working(cloud, robot) -> None:
    with raw(url(cloud, robot.id), additional_headers={"Authorization": f"Token {robot.api_token}"}) as websocket:
        websocket.send('{"op": "subscribe", "topic": ')
        assert "malformed JSON" in next_op(websocket, "status")["msg"]
        websocket.send(json.dumps({"op": "teleport"}))
        assert "unknown op 'teleport'" in next_op(websocket, "status")["msg"]
        websocket.send(json.dumps({"op": "subscribe", "topic": "/chatter", "type": "no_such/Type"}))
        assert "subscribe" in next_op(websocket, "status")["msg"]
        websocket.send(json.dumps({"op": "publish", "topic": "/x", "msg": {"data": "y" * MAX_FRAME}}))
        assert f"exceeds the limit of {MAX_FRAME} bytes" in next_op(websocket, "status")["msg"]
        for index in range(4 * FRAMES_PER_S):  # a flood: over the rate, frames are dropped and it is said once
            websocket.send(json.dumps({"op": "status", "id": index}))
        assert "too many frames" in next_op(websocket, "status")["msg"]
        time.sleep(2.5)  # the bucket refills
        websocket.send(json.dumps({"op": "call_service", "id": "after", "service": "/trigger"}))
        assert next_op(websocket, "service_response")["values"]["message"] == "robot"
    # The robot is as it was: still connected, still serving.
    assert Robot.objects.get(id=robot.id).connected
