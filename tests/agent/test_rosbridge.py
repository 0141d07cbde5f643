"""The robot's rosbridge v2 door, driven by the real roslibpy client against real ROS 1 and ROS 2 nodes."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import time
import xmlrpc.client
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from unittest.mock import ANY

import cbor2
import pytest
import roslibpy
from websockets.sync.client import ClientConnection, connect

from bridgeos_agent.bridges.server import RosbridgeServer
from bridgeos_agent.cli import EXIT_USAGE, main
from bridgeos_agent.ros2graph import rclpy_missing
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.agent.roshelpers import HOST_PYTHON, Nodes, private_rosmaster
from tests.conftest import LoopThread, free_port, wait_until

pytestmark = [pytest.mark.timeout(120)]

FRAME_LIMIT = 1 << 20  # the test server's frame limit, small enough to exceed cheaply
LINGER_S = 0.5  # how long the test server keeps a topic after its last client left


def ros1_available() -> bool:
    return Path(HOST_PYTHON).exists() and Path("/usr/bin/rosmaster").exists()


@dataclass
class Robot:
    """One robot graph with its nodes and a rosbridge server in front of it."""

    ros: str
    server: RosbridgeServer
    loop: LoopThread
    lines: Callable[[str], list[str]]
    call_client_service: Callable[[str], str]
    param: str  # a parameter a node of the graph has

    @property
    def port(self) -> int:
        return self.server.port


@pytest.fixture(scope="module", params=["ros1", "ros2"])
def robot(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    ros = request.param
    home = tmp_path_factory.mktemp(ros)
    loop = LoopThread()
    try:
        if ros == "ros1":
            if not ros1_available():
                pytest.skip("Debian's ROS 1 (rospy, rosmaster) is not installed")
            yield from _ros1_robot(home, loop)
        else:
            if rclpy_missing() is not None:
                pytest.skip("rclpy is not installed")
            yield from _ros2_robot(home, loop)
    finally:
        loop.stop()


def _ros1_robot(home: Path, loop: LoopThread) -> Iterator[Robot]:
    from bridgeos_agent.bridges.ros1graph import Ros1Graph

    with private_rosmaster(home) as master:
        nodes = Nodes(master, home)
        nodes.run("talker", "talker", "--topic", "/chatter", "--rate", "20", "--tag", "robot")
        nodes.run("listener", "listener", "--topic", "/from_client")
        nodes.run("server", "server", "--service", "/trigger", "--tag", "robot")
        nodes.tool("/usr/bin/rosparam", "set", "/robot/gain", "2.5")

        def call_client_service(name: str) -> str:
            done = nodes.tool("/usr/bin/rosservice", "call", name, "data: true", timeout=30)
            return done.stdout + done.stderr

        async def start() -> RosbridgeServer:
            graph = Ros1Graph(master)
            await graph.start()
            server = RosbridgeServer(graph, max_frame_bytes=FRAME_LIMIT, linger_s=LINGER_S)
            await server.start("127.0.0.1", 0)
            return server

        server = loop.run(start())
        try:
            wait_until(lambda: "ready" in nodes.lines("server") and "ready" in nodes.lines("listener"), what="nodes")
            yield Robot("ros1", server, loop, nodes.lines, call_client_service, "/robot/gain")
        finally:
            loop.run(server.close())
            nodes.kill_all()


def _ros2_robot(home: Path, loop: LoopThread) -> Iterator[Robot]:
    from bridgeos_agent.bridges.ros2graph import Ros2BridgeGraph

    graph = loopback_graph()
    nodes = Ros2Nodes(graph, home)
    nodes.run("talker", "talker", "--topic", "/chatter", "--rate", "20", "--tag", "robot", "--linger", "0")
    nodes.run("listener", "listener", "--topic", "/from_client")
    nodes.run("server", "server", "--topic", "/trigger", "--tag", "robot")

    def call_client_service(name: str) -> str:
        nodes.run("caller", "caller", "--topic", name)
        try:
            return wait_until(lambda: "\n".join(nodes.lines("caller")), timeout=30, what="the ROS 2 caller")
        finally:
            nodes.stop("caller")

    async def start() -> RosbridgeServer:
        server = RosbridgeServer(
            Ros2BridgeGraph(graph, asyncio.get_running_loop()), max_frame_bytes=FRAME_LIMIT, linger_s=LINGER_S
        )
        await server.start("127.0.0.1", 0)
        return server

    server = loop.run(start())
    try:
        wait_until(lambda: "ready" in nodes.lines("server") and "ready" in nodes.lines("listener"), what="nodes")
        yield Robot("ros2", server, loop, nodes.lines, call_client_service, "/server_robot:use_sim_time")
    finally:
        loop.run(server.close())
        nodes.kill_all()


@pytest.fixture
def client(robot: Robot) -> Iterator[roslibpy.Ros]:
    ros = roslibpy.Ros("127.0.0.1", robot.port)
    ros.run(timeout=10)
    try:
        yield ros
    finally:
        ros.close()


@pytest.fixture
def raw(robot: Robot) -> Iterator[ClientConnection]:
    with connect(f"ws://127.0.0.1:{robot.port}", max_size=None) as websocket:
        yield websocket


def ask(
    websocket: ClientConnection,
    message: dict[str, Any] | str | bytes,
    op: str = "status",
    match: Callable[[dict[str, Any]], bool] = lambda answer: True,
) -> dict[str, Any]:
    """Send a frame and return the first answer with the given op (and matching ``match``)."""
    websocket.send(message if isinstance(message, str | bytes) else json.dumps(message))
    deadline = time.monotonic() + 15
    while time.monotonic() < deadline:
        frame = websocket.recv(timeout=15)
        answer = json.loads(frame) if isinstance(frame, str) else cbor2.loads(frame)
        if answer["op"] == op and match(answer):
            return answer
    raise AssertionError(f"no {op} answer")


# ---------------------------------------------------------------------- topics


def test_a_client_receives_a_topic_the_robot_publishes(robot: Robot, client: roslibpy.Ros) -> None:
    heard: list[dict[str, Any]] = []
    topic = roslibpy.Topic(client, "/chatter", "std_msgs/String")
    topic.subscribe(heard.append)
    wait_until(lambda: len(heard) >= 5, what="messages from the robot's talker")
    topic.unsubscribe()
    assert all(message["data"].startswith("robot ") for message in heard)
    seqs = [int(message["data"].split()[1]) for message in heard]
    assert seqs == sorted(seqs)


def test_the_robot_is_subscribed_only_while_someone_listens(robot: Robot, client: roslibpy.Ros) -> None:
    topic = roslibpy.Topic(client, "/chatter", "std_msgs/String")
    heard: list[dict[str, Any]] = []
    topic.subscribe(heard.append)
    wait_until(lambda: heard, what="a message")
    assert "/chatter" in robot.server.bridge.subscribed_topics()
    topic.unsubscribe()
    wait_until(lambda: "/chatter" not in robot.server.bridge.subscribed_topics(), what="the graph unsubscription")


def test_a_robot_node_hears_what_a_client_publishes(robot: Robot, client: roslibpy.Ros) -> None:
    topic = roslibpy.Topic(client, "/from_client", "std_msgs/String")
    topic.advertise()

    def heard() -> bool:
        topic.publish(roslibpy.Message({"data": f"client {len(robot.lines('listener'))} {time.time():.6f}"}))
        return any(line.startswith("client ") for line in robot.lines("listener"))

    wait_until(heard, what="the robot's listener to hear the client")
    topic.unadvertise()


def test_throttle_rate_and_queue_length_limit_what_a_client_gets(robot: Robot, client: roslibpy.Ros) -> None:
    throttled: list[dict[str, Any]] = []
    full: list[dict[str, Any]] = []
    slow = roslibpy.Topic(client, "/chatter", "std_msgs/String", throttle_rate=500, queue_length=1)
    slow.subscribe(throttled.append)
    wait_until(lambda: throttled, what="a first throttled message")
    other = roslibpy.Ros("127.0.0.1", robot.port)
    other.run(timeout=10)
    try:
        fast = roslibpy.Topic(other, "/chatter", "std_msgs/String")
        fast.subscribe(full.append)
        start = len(throttled)
        time.sleep(2.0)
        got_throttled, got_full = len(throttled) - start, len(full)
    finally:
        other.close()
    slow.unsubscribe()
    # 20 Hz for 2 s: the unthrottled client gets them all, the throttled one at most one per 500 ms.
    assert got_full >= 25
    assert 2 <= got_throttled <= 6


def test_a_stalled_client_loses_its_own_oldest_messages_only(robot: Robot, client: roslibpy.Ros) -> None:
    stalled = asyncio.Event()  # never set: this client's socket never takes a byte

    async def never(frame: str | bytes) -> None:
        await stalled.wait()

    async def open_stalled() -> Any:
        session = robot.server.bridge.session(never)
        writer = asyncio.get_running_loop().create_task(session.run())
        await session.receive(json.dumps({"op": "subscribe", "topic": "/chatter", "queue_length": 5}))
        return session, writer

    session, writer = robot.loop.run(open_stalled())
    heard: list[dict[str, Any]] = []
    try:
        topic = roslibpy.Topic(client, "/chatter", "std_msgs/String")
        topic.subscribe(heard.append)
        wait_until(lambda: session.stats()["/chatter"]["dropped"] >= 10, what="the stalled client's queue to overflow")
        assert len(heard) >= 10  # the healthy client keeps getting everything meanwhile
        stats = session.stats()["/chatter"]
        assert stats["queued"] == 5 and stats["sent"] <= 1
        topic.unsubscribe()
    finally:

        async def close() -> None:
            writer.cancel()
            await session.close()

        robot.loop.run(close())


# ---------------------------------------------------------------------- services


def test_a_client_calls_a_real_ros_service(robot: Robot, client: roslibpy.Ros) -> None:
    service = roslibpy.Service(client, "/trigger", "std_srvs/Trigger")
    assert service.call(roslibpy.ServiceRequest({}), timeout=15) == {"success": True, "message": "robot"}


def test_a_call_to_a_missing_service_fails_with_the_reason(robot: Robot, client: roslibpy.Ros) -> None:
    service = roslibpy.Service(client, "/nobody_serves_this", "std_srvs/Trigger")
    with pytest.raises(roslibpy.core.ServiceException, match="nobody_serves_this"):
        service.call(roslibpy.ServiceRequest({}), timeout=15)


def test_a_robot_node_calls_a_service_the_client_advertises(robot: Robot, client: roslibpy.Ros) -> None:
    asked: list[dict[str, Any]] = []

    def answer(request: dict[str, Any], response: dict[str, Any]) -> bool:
        asked.append(dict(request))
        response["success"] = request["data"]
        response["message"] = "answered by the client"
        return True

    service = roslibpy.Service(client, "/client_switch", "std_srvs/SetBool")
    service.advertise(answer)
    wait_until(lambda: "/client_switch" in robot.server.bridge.client_services(), what="the advertisement")
    output = robot.call_client_service("/client_switch")
    service.unadvertise()
    assert asked == [{"data": True}]
    assert "answered by the client" in output and ("True" in output or "true" in output)


# ---------------------------------------------------------------------- rosapi


def test_rosapi_lists_the_graph(robot: Robot, client: roslibpy.Ros) -> None:
    string = "std_msgs/String" if robot.ros == "ros1" else "std_msgs/msg/String"
    assert "/chatter" in client.get_topics()
    assert client.get_topic_type("/chatter") == string
    assert "/chatter" in client.get_topics_for_type(string)
    services = client.get_services()
    assert "/trigger" in services and "/rosapi/topics" in services
    assert client.get_service_type("/trigger") in ("std_srvs/Trigger", "std_srvs/srv/Trigger")
    assert any("server" in node for node in client.get_nodes())
    now = client.get_time()
    assert abs(now.secs + now.nsecs * 1e-9 - time.time()) < 5
    details = client.get_message_details("geometry_msgs/Pose")["typedefs"]
    assert details[0]["fieldnames"] == ["position", "orientation"]
    assert {"x", "y", "z"} <= set(details[1]["fieldnames"])


def test_params_are_read_written_and_listed(robot: Robot, client: roslibpy.Ros) -> None:
    if robot.ros == "ros1":
        assert client.get_param("/robot/gain") == 2.5
        client.set_param("/robot/limits", {"speed": [1, 2]})
        assert client.get_param("/robot/limits") == {"speed": [1, 2]}
        assert "/robot/limits/speed" in client.get_params()
        client.delete_param("/robot/limits")
        assert client.get_param("/robot/limits") is None
    else:
        assert client.get_param(robot.param) is False
        client.set_param(robot.param, True)
        assert client.get_param(robot.param) is True
        client.set_param(robot.param, False)
        assert robot.param in client.get_params()
        with pytest.raises(roslibpy.core.ServiceException, match="belong to nodes"):
            client.get_param("use_sim_time")


# ---------------------------------------------------------------------- encodings and bad input


def test_cbor_subscribers_get_binary_frames(robot: Robot, raw: ClientConnection) -> None:
    cbor = ask(raw, {"op": "subscribe", "topic": "/chatter", "compression": "cbor"}, op="publish")
    assert cbor["msg"]["data"].startswith("robot ")
    raw.send(json.dumps({"op": "unsubscribe", "topic": "/chatter"}))
    subscribe = cbor2.dumps({"op": "subscribe", "id": "r", "topic": "/chatter", "compression": "cbor-raw"})
    packed = ask(raw, subscribe, "publish", match=lambda answer: "bytes" in answer["msg"])
    assert isinstance(packed["msg"]["bytes"], bytes) and b"robot " in packed["msg"]["bytes"]
    assert packed["msg"]["secs"] > 0


@pytest.mark.parametrize(
    ("frame", "says"),
    [
        ("{not json", "malformed JSON"),
        ('["op", "publish"]', "must be an object"),
        ({"op": "fly", "id": "f1"}, "unknown op 'fly'"),
        ({"op": "subscribe", "id": "s1", "topic": "/nobody_publishes"}, "/nobody_publishes does not exist"),
        ({"op": "subscribe", "topic": "/chatter", "compression": "png"}, "compression 'png' is not supported"),
        ({"op": "subscribe", "topic": "/chatter", "throttle_rate": -5}, "'throttle_rate' must be a number >= 0"),
        ({"op": "advertise", "topic": "/x", "type": "nope_msgs/Nope"}, "nope_msgs"),
        ({"op": "advertise", "topic": "/chatter", "type": "std_msgs/Int32"}, "/chatter already exists with type"),
        ({"op": "publish", "topic": "/nowhere", "msg": {}}, "/nowhere does not exist"),
        ({"op": "publish", "topic": "/from_client", "msg": {"dta": "typo"}}, "no field 'dta'"),
        ({"op": "publish", "topic": "/from_client", "msg": {"data": 7}}, "data"),
        ({"op": "call_service", "service": "/trigger", "args": 5}, "'args' must be an object"),
        ({"op": "advertise_service", "service": "/trigger", "type": "std_srvs/Trigger"}, "already served"),
        ({"op": "service_response", "id": "nobody", "values": {}}, "no call is waiting"),
        ({"op": "set_level", "level": "loud"}, "level must be one of"),
        ("x" * (FRAME_LIMIT + 10), f"exceeds the limit of {FRAME_LIMIT}"),
    ],
)
def test_bad_input_gets_a_status_naming_it_and_the_connection_keeps_working(
    frame: dict[str, Any] | str, says: str, robot: Robot, raw: ClientConnection
) -> None:
    status = ask(raw, frame)
    assert status["level"] == "error"
    assert says in status["msg"]
    if isinstance(frame, dict) and "id" in frame:
        assert status["id"] == frame["id"]
    answer = ask(raw, {"op": "call_service", "id": "after", "service": "/rosapi/topics"}, op="service_response")
    assert answer["result"] is True and "/chatter" in answer["values"]["topics"]


def test_a_flood_of_bad_frames_is_answered_and_the_robot_keeps_serving(robot: Robot, raw: ClientConnection) -> None:
    for index in range(500):
        raw.send(json.dumps({"op": "nonsense", "id": index}))
    answered = 0
    while True:
        answer = json.loads(raw.recv(timeout=15))
        if answer["op"] == "status":
            answered += 1
        if answered == 500:
            break
    assert ask(raw, {"op": "call_service", "id": "ok", "service": "/trigger"}, op="service_response")["result"]


def test_warnings_come_only_once_the_client_asks_for_them(robot: Robot, raw: ClientConnection) -> None:
    raw.send(json.dumps({"op": "unadvertise", "topic": "/never_advertised"}))  # a warning: not sent at "error"
    raw.send(json.dumps({"op": "set_level", "level": "warning"}))
    status = ask(raw, {"op": "unadvertise", "id": "u", "topic": "/never_advertised"})
    assert status == {
        "op": "status",
        "level": "warning",
        "msg": "unadvertise: /never_advertised is not advertised by this client",
        "id": "u",
    }


# ---------------------------------------------------------------------- the agent's door


ROBOT_ARGS = ["run", "--master", "ws://127.0.0.1:9", "--robot", "rb-door", "--token", "t" * 20]


@pytest.mark.parametrize(
    ("args", "env", "says"),
    [
        (["--rosbridge", "9090"], {}, "is not HOST:PORT"),
        (["--rosbridge", "127.0.0.1:99999"], {}, "outside 0-65535"),
        (["--rosbridge", "127.0.0.1:0"], {}, "give a port"),
        (["--rosbridge", "127.0.0.1:nine"], {}, "is not a number"),
        ([], {"BRIDGEOS_ROSBRIDGE": "localhost"}, "is not HOST:PORT"),
        (["--rosbridge", "127.0.0.1:9090"], {"BRIDGEOS_ROSBRIDGE_ROS": "ros3"}, "must be auto, ros1 or ros2"),
    ],
)
def test_a_bad_rosbridge_option_is_refused_before_anything_starts(
    args: list[str], env: dict[str, str], says: str, monkeypatch: pytest.MonkeyPatch, capsys, tmp_path: Path
) -> None:
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    data_dir = tmp_path / "data"
    assert main([*ROBOT_ARGS, "--data-dir", str(data_dir), *args]) == EXIT_USAGE
    assert says in capsys.readouterr().err
    assert not data_dir.exists()


ROSBRIDGE_PORT = 9090  # rosbridge's well-known port, which roslibpy's and roslibjs's examples assume


@pytest.mark.skipif(not ros1_available(), reason="Debian's ROS 1 is not installed")
@pytest.mark.parametrize("well_known", [False, True], ids=["free port", "port 9090"])
def test_the_agent_serves_rosbridge_when_asked(tmp_path: Path, well_known: bool) -> None:
    # On rosbridge's own port too: nothing this project starts (its Prometheus once did) may hold it.
    with private_rosmaster(tmp_path) as master:
        port = ROSBRIDGE_PORT if well_known else free_port()
        env = {**os.environ, "ROS_MASTER_URI": master, "PYTHONUNBUFFERED": "1"}
        agent = subprocess.Popen(
            [
                *(sys.executable, "-m", "bridgeos_agent.cli", *ROBOT_ARGS, "--data-dir", str(tmp_path / "data")),
                *("--runtime", "process", "--simulate", "--rosbridge", f"127.0.0.1:{port}"),
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=(tmp_path / "agent.err").open("wb"),
        )
        try:
            wait_until(lambda: "rosbridge v2 for the robot's ROS1 graph" in (tmp_path / "agent.err").read_text(), 30)
            ros = roslibpy.Ros("127.0.0.1", port)
            ros.run(timeout=10)
            try:
                assert "/rosapi/topics" in ros.get_services()
                ros.set_param("/door/opened", True)  # lands in the private master's parameter server
                assert xmlrpc.client.ServerProxy(master).getParam("/test", "/door/opened") == [1, ANY, True]
            finally:
                ros.close()
        finally:
            agent.terminate()
            agent.wait(20)
