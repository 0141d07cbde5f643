"""The robot's Foxglove WebSocket door, driven by the real @foxglove/ws-protocol client (Node) against real ROS nodes."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import struct
import subprocess
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from bridgeos_agent.bridges.foxglove import SUBPROTOCOLS
from bridgeos_agent.bridges.server import FoxgloveServer
from bridgeos_agent.cli import EXIT_USAGE, main
from bridgeos_agent.ros2graph import rclpy_missing
from tests.agent.foxgloveclient import FoxgloveClient, node_client_ready
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.agent.roshelpers import HOST_PYTHON, Nodes, private_rosmaster
from tests.conftest import LoopThread, free_port, wait_until

pytestmark = [pytest.mark.timeout(120)]

FRAME_LIMIT = 1 << 20


if not node_client_ready():
    pytest.skip(
        "node or tests/js/foxglove/node_modules is missing: run scripts/services.sh node", allow_module_level=True
    )


@dataclass
class Robot:
    ros: str
    server: FoxgloveServer
    loop: LoopThread
    lines: Callable[[str], list[str]]
    run_talker: Callable[[str, str], subprocess.Popen[bytes] | None]

    @property
    def port(self) -> int:
        return self.server.port

    @property
    def encoding(self) -> str:
        return "ros1" if self.ros == "ros1" else "cdr"

    def type(self, name: str) -> str:
        package, short = name.split("/")
        return name if self.ros == "ros1" else f"{package}/msg/{short}"


@pytest.fixture(scope="module", params=["ros1", "ros2"])
def robot(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    ros = request.param
    home = tmp_path_factory.mktemp(f"foxglove-{ros}")
    loop = LoopThread()
    try:
        if ros == "ros1":
            if not (Path(HOST_PYTHON).exists() and Path("/usr/bin/rosmaster").exists()):
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

        def run_talker(key: str, topic: str) -> subprocess.Popen[bytes]:
            args = ("--rate", "20", "--count", "60", "--linger", "0", "--tag", key)
            return nodes.run(key, "talker", "--topic", topic, *args)

        async def start() -> FoxgloveServer:
            graph = Ros1Graph(master, name="/bridgeos_foxglove")
            await graph.start()
            server = FoxgloveServer(graph, max_frame_bytes=FRAME_LIMIT, linger_s=0.5, poll_s=0.5)
            await server.start("127.0.0.1", 0)
            return server

        server = loop.run(start())
        try:
            wait_until(lambda: "ready" in nodes.lines("server") and "ready" in nodes.lines("listener"), what="nodes")
            yield Robot("ros1", server, loop, nodes.lines, run_talker)
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

    def run_talker(key: str, topic: str) -> None:
        # 10 s of life: an rclpy node's start and its discovery took over 3 s on a slow machine,
        # and a talker of 3 s was gone before the graph was polled (never advertised).
        nodes.run(key, "talker", "--topic", topic, "--rate", "20", "--count", "200", "--linger", "0", "--tag", key)

    async def start() -> FoxgloveServer:
        bridge_graph = Ros2BridgeGraph(graph, asyncio.get_running_loop(), name="bridgeos_foxglove")
        server = FoxgloveServer(bridge_graph, max_frame_bytes=FRAME_LIMIT, linger_s=0.5, poll_s=0.5)
        await server.start("127.0.0.1", 0)
        return server

    server = loop.run(start())
    try:
        wait_until(lambda: "ready" in nodes.lines("server") and "ready" in nodes.lines("listener"), what="nodes")
        yield Robot("ros2", server, loop, nodes.lines, run_talker)
    finally:
        loop.run(server.close())
        nodes.kill_all()


@pytest.fixture
def client(robot: Robot) -> Iterator[FoxgloveClient]:
    client = FoxgloveClient(robot.port)
    try:
        client.wait("open")
        yield client
    finally:
        client.close()


def decoder(robot: Robot, schema_name: str, schema: str) -> Callable[[bytes], Any]:
    """Return a decoder built from an advertised schema alone, as a Foxglove client builds one."""
    if robot.ros == "ros1":
        from mcap_ros1._vendor.genpy.dynamic import generate_dynamic as ros1_dynamic

        cls = ros1_dynamic(schema_name, schema)[schema_name]
        return lambda raw: cls().deserialize(raw)
    from mcap_ros2._dynamic import generate_dynamic as ros2_dynamic

    return ros2_dynamic(schema_name, schema)[schema_name]


def encoder(robot: Robot, schema_name: str, schema: str) -> Callable[[dict[str, Any]], bytes]:
    """Return an encoder built from a schema alone, as a Foxglove client publishes with one."""
    if robot.ros == "ros1":
        import io

        from mcap_ros1._vendor.genpy.dynamic import generate_dynamic as ros1_dynamic

        cls = ros1_dynamic(schema_name, schema)[schema_name]

        def encode(fields: dict[str, Any]) -> bytes:
            buffer = io.BytesIO()
            cls(**fields).serialize(buffer)
            return buffer.getvalue()

        return encode
    from mcap_ros2._dynamic import serialize_dynamic

    return serialize_dynamic(schema_name, schema)[schema_name]


# ---------------------------------------------------------------------- connecting


def test_the_server_says_what_it_offers_and_advertises_topics_with_schemas_that_parse(
    robot: Robot, client: FoxgloveClient
) -> None:
    info = client.wait("serverInfo")["info"]
    assert {"clientPublish", "services"} <= set(info["capabilities"])
    assert info["supportedEncodings"][0] == robot.encoding
    assert info["metadata"]["ROS_VERSION"] == robot.ros[-1]
    chatter = client.channel("/chatter")
    assert chatter["encoding"] == robot.encoding
    assert chatter["schemaName"] == robot.type("std_msgs/String")
    assert chatter["schemaEncoding"] == ("ros1msg" if robot.ros == "ros1" else "ros2msg")
    assert "string data" in chatter["schema"]
    decoder(robot, chatter["schemaName"], chatter["schema"])  # parses
    trigger = client.service("/trigger")
    assert trigger["type"] in ("std_srvs/Trigger", "std_srvs/srv/Trigger")
    assert "bool success" in trigger["response"]["schema"] and trigger["request"]["encoding"] == robot.encoding


def test_a_schema_with_nested_types_carries_every_definition(robot: Robot) -> None:
    schema = robot.server.graph.schema(robot.type("geometry_msgs/PoseStamped"))
    sections = schema.split("=" * 80 + "\nMSG: ")
    names = {section.split("\n", 1)[0] for section in sections[1:]}
    header = "std_msgs/Header" if robot.ros == "ros1" else "std_msgs/msg/Header"
    assert header in names and robot.type("geometry_msgs/Quaternion") in names
    decode = decoder(robot, robot.type("geometry_msgs/PoseStamped"), schema)
    assert decode is not None


@pytest.mark.parametrize("subprotocol", SUBPROTOCOLS)
def test_both_subprotocols_are_accepted_and_echoed(robot: Robot, subprotocol: str) -> None:
    client = FoxgloveClient(robot.port, subprotocol)
    try:
        assert client.wait("open")["protocol"] == subprotocol
        assert client.wait("serverInfo")["info"]["name"]
    finally:
        client.close()


# ---------------------------------------------------------------------- topics


def test_a_client_receives_the_robots_talker_as_raw_bytes_that_decode(robot: Robot, client: FoxgloveClient) -> None:
    chatter = client.channel("/chatter")
    client.command("subscribe", topic="/chatter")
    subscription = client.wait("subscribed")["subscriptionId"]
    decode = decoder(robot, chatter["schemaName"], chatter["schema"])
    texts = []
    for _ in range(5):
        message = client.wait("message", lambda e: e["subscriptionId"] == subscription)
        assert abs(int(message["timestamp"]) / 1e9 - time.time()) < 10
        texts.append(decode(base64.b64decode(message["data"])).data)
    assert all(text.startswith("robot ") for text in texts)
    seqs = [int(text.split()[1]) for text in texts]
    assert seqs == sorted(seqs)
    assert "/chatter" in robot.server.bridge.fanouts.topics()
    client.command("unsubscribe", subscriptionId=subscription)
    wait_until(lambda: "/chatter" not in robot.server.bridge.fanouts.topics(), what="the graph unsubscription")


def test_a_topic_that_appears_is_advertised_and_one_that_goes_is_withdrawn(
    robot: Robot, client: FoxgloveClient
) -> None:
    robot.run_talker("brief", "/brief")
    channel = client.channel("/brief")
    gone = client.wait("unadvertise", lambda e: channel["id"] in e["channelIds"], timeout=30)
    assert gone["channelIds"] == [channel["id"]]


def test_a_client_publishes_to_a_real_listener(robot: Robot, client: FoxgloveClient) -> None:
    type_ = robot.type("std_msgs/String")
    client.command("advertise", topic="/from_client", encoding=robot.encoding, schemaName=type_)
    channel_id = client.wait("advertised")["channelId"]
    encode = encoder(robot, type_, robot.server.graph.schema(type_))

    def heard() -> bool:
        data = encode({"data": f"viewer {len(robot.lines('listener'))} {time.time():.6f}"})
        client.command("publish", channelId=channel_id, data=base64.b64encode(data).decode())
        return any(line.startswith("viewer ") for line in robot.lines("listener"))

    wait_until(heard, what="the robot's listener to hear the Foxglove client")
    client.command("unadvertise", channelId=channel_id)


def test_a_client_publishes_json_too(robot: Robot, client: FoxgloveClient) -> None:
    client.command("advertise", topic="/from_client", encoding="json", schemaName=robot.type("std_msgs/String"))
    channel_id = client.wait("advertised")["channelId"]

    def heard() -> bool:
        data = json.dumps({"data": f"jsonviewer {len(robot.lines('listener'))} {time.time():.6f}"}).encode()
        client.command("publish", channelId=channel_id, data=base64.b64encode(data).decode())
        return any(line.startswith("jsonviewer ") for line in robot.lines("listener"))

    wait_until(heard, what="the robot's listener to hear JSON from the client")


def test_a_stalled_client_loses_its_own_oldest_messages_only(robot: Robot, client: FoxgloveClient) -> None:
    stalled = asyncio.Event()  # never set: this client's socket never takes a byte

    async def never(frame: str | bytes) -> None:
        await stalled.wait()

    chatter = client.channel("/chatter")

    async def open_stalled() -> Any:
        session = robot.server.bridge.session(never)
        writer = asyncio.get_running_loop().create_task(session.run())
        subscribe = {"op": "subscribe", "subscriptions": [{"id": 7, "channelId": chatter["id"]}]}
        await session.receive(json.dumps(subscribe))
        return session, writer

    session, writer = robot.loop.run(open_stalled())
    try:
        client.command("subscribe", topic="/chatter")
        subscription = client.wait("subscribed")["subscriptionId"]
        wait_until(
            lambda: session.stats()["/chatter"]["dropped"] >= 5, timeout=30, what="the stalled queue to overflow"
        )
        for _ in range(10):  # the healthy client keeps getting messages meanwhile
            client.wait("message", lambda e: e["subscriptionId"] == subscription)
        stats = session.stats()["/chatter"]
        assert stats["queued"] == robot.server.bridge.default_queue and stats["sent"] <= 1
    finally:

        async def close() -> None:
            writer.cancel()
            await session.close()

        robot.loop.run(close())


# ---------------------------------------------------------------------- services


def trigger_request(robot: Robot, client: FoxgloveClient) -> tuple[dict[str, Any], bytes]:
    service = client.service("/trigger")
    request = service["request"]
    return service, encoder(robot, request["schemaName"], request["schema"])({})


def test_a_service_call_gets_the_real_answer(robot: Robot, client: FoxgloveClient) -> None:
    service, request = trigger_request(robot, client)
    client.command(
        "call", service="/trigger", callId=41, encoding=robot.encoding, data=base64.b64encode(request).decode()
    )
    answer = client.wait("serviceCallResponse", lambda e: e["callId"] == 41)
    assert answer["serviceId"] == service["id"] and answer["encoding"] == robot.encoding
    response = service["response"]
    decoded = decoder(robot, response["schemaName"], response["schema"])(base64.b64decode(answer["data"]))
    assert (decoded.success, decoded.message) == (True, "robot")


def test_a_service_call_in_json_gets_a_json_answer(robot: Robot, client: FoxgloveClient) -> None:
    client.service("/trigger")
    client.command("call", service="/trigger", callId=42, encoding="json", data=base64.b64encode(b"{}").decode())
    answer = client.wait("serviceCallResponse", lambda e: e["callId"] == 42)
    assert json.loads(base64.b64decode(answer["data"])) == {"success": True, "message": "robot"}


def test_a_call_that_cannot_be_made_fails_with_the_reason(robot: Robot, client: FoxgloveClient) -> None:
    client.wait("serverInfo")
    frame = struct.pack("<BIII", 0x02, 99_999, 5, 4) + b"json{}"
    client.command("raw", binary=base64.b64encode(frame).decode())
    failure = client.wait("serviceCallFailure")["failure"]
    assert failure == {"op": "serviceCallFailure", "serviceId": 99_999, "callId": 5, "message": failure["message"]}
    assert "no service 99999" in failure["message"]
    client.service("/trigger")
    client.command("call", service="/trigger", callId=6, encoding="json", data=base64.b64encode(b"{").decode())
    failure = client.wait("serviceCallFailure", lambda e: e["failure"]["callId"] == 6)["failure"]
    assert "/trigger" in failure["message"] and "not JSON" in failure["message"]


# ---------------------------------------------------------------------- bad input


def binary(*parts: bytes) -> dict[str, str]:
    return {"binary": base64.b64encode(b"".join(parts)).decode()}


@pytest.mark.parametrize(
    ("frame", "says", "level"),
    [
        ({"text": "{not json"}, "malformed JSON", 2),
        ({"text": '["op"]'}, "must be a JSON object with an 'op'", 2),
        ({"text": '{"op": "fly"}'}, "unknown op 'fly'", 2),
        ({"text": '{"op": "subscribeConnectionGraph"}'}, "subscribeConnectionGraph is not supported", 2),
        ({"text": '{"op": "subscribe"}'}, "'subscriptions' is missing", 2),
        ({"text": '{"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 77777}]}'}, "no channel 77777", 2),
        ({"text": '{"op": "subscribe", "subscriptions": [{"id": -1, "channelId": 1}]}'}, "must be an integer", 2),
        ({"text": '{"op": "unsubscribe", "subscriptionIds": [424242]}'}, "no subscription 424242", 1),
        (
            {
                "text": '{"op": "advertise", "channels": [{"id": 3, "topic": "/x", "encoding": "protobuf", "schemaName": "a/B"}]}'
            },
            "encoding 'protobuf' is not one of",
            2,
        ),
        (
            {
                "text": '{"op": "advertise", "channels": [{"id": 3, "topic": "/x", "encoding": "json", "schemaName": "nope_msgs/Nope"}]}'
            },
            "nope_msgs",
            2,
        ),
        ({"text": '{"op": "unadvertise", "channelIds": [9]}'}, "channel 9 is not advertised", 1),
        (binary(b"\x01", struct.pack("<I", 12345), b"payload"), "channel 12345 is not advertised", 2),
        (binary(b"\x01\x00"), "too short", 2),
        (binary(b"\x09abc"), "unknown binary opcode 0x09", 2),
        (binary(b"\x02", struct.pack("<III", 1, 1, 1000)), "runs past the frame's end", 2),
        ({"text": "x" * (FRAME_LIMIT + 10)}, f"exceeds the limit of {FRAME_LIMIT}", 2),
    ],
)
def test_bad_input_gets_a_status_naming_it_and_the_connection_keeps_working(
    frame: dict[str, str], says: str, level: int, robot: Robot, client: FoxgloveClient
) -> None:
    client.wait("serverInfo")
    client.command("raw", **frame)
    assert client.status(says)["level"] == level
    client.service("/trigger")
    client.command("call", service="/trigger", callId=1, encoding="json", data=base64.b64encode(b"{}").decode())
    assert client.wait("serviceCallResponse", lambda e: e["callId"] == 1)


def test_a_client_message_that_does_not_read_is_refused(robot: Robot, client: FoxgloveClient) -> None:
    client.command("advertise", topic="/from_client", encoding=robot.encoding, schemaName=robot.type("std_msgs/String"))
    channel_id = client.wait("advertised")["channelId"]
    client.command("publish", channelId=channel_id, data=base64.b64encode(b"\xff\xff\xff\x7f").decode())
    assert "/from_client" in client.status("/from_client")["message"]


def test_a_flood_of_bad_frames_is_answered_and_the_robot_keeps_serving(robot: Robot, client: FoxgloveClient) -> None:
    client.wait("serverInfo")
    for index in range(300):
        client.command("raw", text=json.dumps({"op": "nonsense", "n": index}))
    for _ in range(300):
        client.wait("status", lambda e: "unknown op 'nonsense'" in e["status"]["message"])
    client.service("/trigger")
    client.command("call", service="/trigger", callId=2, encoding="json", data=base64.b64encode(b"{}").decode())
    assert client.wait("serviceCallResponse", lambda e: e["callId"] == 2)


# ---------------------------------------------------------------------- the agent's door


ROBOT_ARGS = ["run", "--master", "ws://127.0.0.1:9", "--robot", "rb-door", "--token", "t" * 20]


@pytest.mark.parametrize(
    ("args", "env", "says"),
    [
        (["--foxglove", "8765"], {}, "is not HOST:PORT"),
        (["--foxglove", "127.0.0.1:99999"], {}, "outside 0-65535"),
        (["--foxglove", "127.0.0.1:0"], {}, "give a port (the usual one is 8765)"),
        ([], {"BRIDGEOS_FOXGLOVE": "localhost"}, "is not HOST:PORT"),
        (["--foxglove", "127.0.0.1:8765"], {"BRIDGEOS_FOXGLOVE_ROS": "ros3"}, "must be auto, ros1 or ros2"),
        (["--foxglove", "127.0.0.1:8765", "--rosbridge", "127.0.0.1:8765"], {}, "cannot share"),
    ],
)
def test_a_bad_foxglove_option_is_refused_before_anything_starts(
    args: list[str], env: dict[str, str], says: str, monkeypatch: pytest.MonkeyPatch, capsys, tmp_path: Path
) -> None:
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    data_dir = tmp_path / "data"
    assert main([*ROBOT_ARGS, "--data-dir", str(data_dir), *args]) == EXIT_USAGE
    assert says in capsys.readouterr().err
    assert not data_dir.exists()


@pytest.mark.skipif(not Path("/usr/bin/rosmaster").exists(), reason="Debian's ROS 1 is not installed")
def test_the_agent_serves_foxglove_when_asked(tmp_path: Path) -> None:
    with private_rosmaster(tmp_path) as master:
        port = free_port()
        env = {**os.environ, "ROS_MASTER_URI": master, "PYTHONUNBUFFERED": "1"}
        agent = subprocess.Popen(
            [
                *(sys.executable, "-m", "bridgeos_agent.cli", *ROBOT_ARGS, "--data-dir", str(tmp_path / "data")),
                *("--runtime", "process", "--simulate", "--foxglove", f"127.0.0.1:{port}"),
            ],
            env=env,
            stdout=subprocess.DEVNULL,
            stderr=(tmp_path / "agent.err").open("wb"),
        )
        nodes = Nodes(master, tmp_path)
        nodes.run("talker", "talker", "--topic", "/chatter", "--rate", "5", "--tag", "door")
        try:
            wait_until(
                lambda: "Foxglove WebSocket for the robot's ROS1 graph" in (tmp_path / "agent.err").read_text(), 30
            )
            client = FoxgloveClient(port)
            try:
                assert client.wait("serverInfo")["info"]["supportedEncodings"][0] == "ros1"
                assert client.channel("/chatter", timeout=30)["schemaName"] == "std_msgs/String"
            finally:
                client.close()
        finally:
            agent.terminate()
            agent.wait(20)
            nodes.kill_all()
