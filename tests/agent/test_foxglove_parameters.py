"""Foxglove's parameters and time capabilities on the robot's door, driven by the real @foxglove/ws-protocol client.

ROS 1: the master's parameter server; ROS 2: a real rclpy node's declared parameters, named
/node:parameter. Time: a graph on simulated time (ROS 1's /use_sim_time with a /clock publisher,
or a ROS 2 node publishing /clock in a domain of its own, so no other test's graph sees it).
"""

from __future__ import annotations

import asyncio
import json
import os
import time
import xmlrpc.client
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from bridgeos_agent.bridges.server import FoxgloveServer
from bridgeos_agent.ros2graph import Ros2Graph, rclpy_missing
from tests.agent.foxgloveclient import FoxgloveClient, node_client_ready
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.agent.roshelpers import Nodes, private_rosmaster
from tests.agent.test_rosbridge import ros1_available
from tests.agent.test_rosbridge_actions import run_action_server
from tests.conftest import LoopThread, wait_until

pytestmark = [pytest.mark.timeout(120)]

if not node_client_ready():
    pytest.skip(
        "node or tests/js/foxglove/node_modules is missing: run scripts/services.sh node", allow_module_level=True
    )

PARAM_POLL_S = 0.2
VALUES = {
    "gain": 2.5,
    "count": 3,
    "label": "robot",
    "enabled": True,
    "limits": [1.0, 2.0],
    "tags": ["a", "b"],
    "blob": b"\x01\x02",
}


@dataclass
class Robot:
    ros: str
    server: FoxgloveServer
    loop: LoopThread
    prefix: str  # a parameter's full name is prefix + its short name

    @property
    def port(self) -> int:
        return self.server.port

    def name(self, short: str) -> str:
        return self.prefix + short

    def values(self, *shorts: str) -> dict[str, Any]:
        """Read parameters straight from the graph (not through a Foxglove client)."""
        found = self.loop.run(self.server.graph.get_params([self.name(s) for s in shorts]))
        return {name.removeprefix(self.prefix): value for name, value in found.items()}

    def set(self, short: str, value: Any) -> None:
        """Change a parameter behind the clients' backs."""
        self.loop.run(self.server.graph.set_param(self.name(short), value))


@pytest.fixture(scope="module", params=["ros1", "ros2"])
def robot(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    home = tmp_path_factory.mktemp(f"params-{request.param}")
    loop = LoopThread()
    try:
        if request.param == "ros1":
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
        proxy = xmlrpc.client.ServerProxy(master)
        for short, value in VALUES.items():
            proxy.setParam(
                "/test", f"/robot/{short}", xmlrpc.client.Binary(value) if isinstance(value, bytes) else value
            )

        async def start() -> FoxgloveServer:
            graph = Ros1Graph(master, name="/bridgeos_foxglove")
            await graph.start()
            server = FoxgloveServer(graph, poll_s=0.5, param_poll_s=PARAM_POLL_S)
            await server.start("127.0.0.1", 0)
            return server

        server = loop.run(start())
        try:
            yield Robot("ros1", server, loop, "/robot/")
        finally:
            loop.run(server.close())


def _ros2_robot(home: Path, loop: LoopThread) -> Iterator[Robot]:
    from bridgeos_agent.bridges.ros2graph import Ros2BridgeGraph

    graph = loopback_graph()
    nodes = Ros2Nodes(graph, home)
    node = f"fg_params_{os.getpid()}"
    run_action_server(nodes, "params", "--name", node, "--action", f"/{node}_action", "--params")

    async def start() -> FoxgloveServer:
        bridge_graph = Ros2BridgeGraph(graph, asyncio.get_running_loop(), name="bridgeos_foxglove_params")
        server = FoxgloveServer(bridge_graph, poll_s=0.5, param_poll_s=PARAM_POLL_S)
        await server.start("127.0.0.1", 0)
        return server

    server = loop.run(start())
    try:
        wait_until(lambda: "ready" in nodes.lines("params"), what="the parameter node")
        robot = Robot("ros2", server, loop, f"/{node}:")
        wait_until(lambda: robot.values("gain"), timeout=20, what="the node's parameter services")
        yield robot
    finally:
        loop.run(server.close())
        nodes.kill_all()


@pytest.fixture
def client(robot: Robot) -> Iterator[FoxgloveClient]:
    client = FoxgloveClient(robot.port)
    try:
        client.wait("serverInfo")
        yield client
    finally:
        client.close()
        for short, value in VALUES.items():  # what a test changed is put back for the next
            if robot.values(short).get(short) != value:
                robot.set(short, value)


def entries(event: dict[str, Any], robot: Robot) -> dict[str, dict[str, Any]]:
    return {p["name"].removeprefix(robot.prefix): p for p in event["parameters"]}


# ---------------------------------------------------------------------- reading and writing


def test_the_server_offers_parameters_and_no_time_on_a_wall_clock(robot: Robot) -> None:
    client = FoxgloveClient(robot.port)
    try:
        capabilities = client.wait("serverInfo")["info"]["capabilities"]
    finally:
        client.close()
    assert {"parameters", "parametersSubscribe", "clientPublish", "services"} <= set(capabilities)
    assert "time" not in capabilities


def test_parameters_are_read_with_their_types(robot: Robot, client: FoxgloveClient) -> None:
    client.command("getParameters", names=[robot.name(short) for short in VALUES], id="g1")
    answer = client.wait("parameterValues", lambda e: e["id"] == "g1")
    assert entries(answer, robot) == {
        "gain": {"name": robot.name("gain"), "value": 2.5, "type": "float64"},
        "count": {"name": robot.name("count"), "value": 3},
        "label": {"name": robot.name("label"), "value": "robot"},
        "enabled": {"name": robot.name("enabled"), "value": True},
        "limits": {"name": robot.name("limits"), "value": [1, 2], "type": "float64_array"},
        "tags": {"name": robot.name("tags"), "value": ["a", "b"]},
        "blob": {"name": robot.name("blob"), "value": "AQI=", "type": "byte_array"},
    }


def test_every_parameter_comes_when_none_is_named(robot: Robot, client: FoxgloveClient) -> None:
    client.command("getParameters", names=[], id="all")
    names = {p["name"] for p in client.wait("parameterValues", lambda e: e["id"] == "all")["parameters"]}
    assert {robot.name(short) for short in VALUES} <= names


def test_an_unknown_parameter_is_told_and_the_others_answered(robot: Robot, client: FoxgloveClient) -> None:
    client.command("getParameters", names=[robot.name("gain"), robot.name("nope")], id="g2")
    answer = client.wait("parameterValues", lambda e: e["id"] == "g2")
    assert list(entries(answer, robot)) == ["gain"]
    status = client.status(f"no parameter {robot.name('nope')}")
    assert status["level"] == 1


def test_parameters_are_set_and_their_new_values_answered(robot: Robot, client: FoxgloveClient) -> None:
    parameters = [
        {"name": robot.name("gain"), "value": 4, "type": "float64"},
        {"name": robot.name("label"), "value": "arm"},
        {"name": robot.name("limits"), "value": [0.5, 4], "type": "float64_array"},
        {"name": robot.name("blob"), "value": "AwQF", "type": "byte_array"},
        {"name": robot.name("enabled"), "value": False},
    ]
    client.command("setParameters", parameters=parameters, id="s1")
    answer = entries(client.wait("parameterValues", lambda e: e["id"] == "s1"), robot)
    assert answer["gain"]["value"] == 4 and answer["gain"]["type"] == "float64"
    assert answer["blob"]["value"] == "AwQF" and answer["enabled"]["value"] is False
    assert robot.values("gain", "label", "limits", "blob", "enabled") == {
        "gain": 4.0,
        "label": "arm",
        "limits": [0.5, 4.0],
        "blob": b"\x03\x04\x05",
        "enabled": False,
    }


def test_a_whole_number_for_a_double_parameter_keeps_it_a_double(robot: Robot, client: FoxgloveClient) -> None:
    # JavaScript has one number type: 3.0 arrives as 3, and the parameter must stay a double.
    client.command("setParameters", parameters=[{"name": robot.name("gain"), "value": 3}], id="s2")
    client.wait("parameterValues", lambda e: e["id"] == "s2")
    value = robot.values("gain")["gain"]
    assert value == 3.0 and isinstance(value, float)


def test_on_ros1_a_parameter_is_unset_by_leaving_out_its_value(robot: Robot, client: FoxgloveClient) -> None:
    if robot.ros == "ros2":
        pytest.skip("a ROS 2 node's declared parameters cannot be undeclared from outside (among the refusals)")
    robot.set("scratch", 1)
    client.command("setParameters", parameters=[{"name": robot.name("scratch")}], id="u1")
    assert client.wait("parameterValues", lambda e: e["id"] == "u1")["parameters"] == [{"name": robot.name("scratch")}]
    assert robot.values("scratch") == {}


# ---------------------------------------------------------------------- updates


def test_a_subscribed_parameter_is_sent_when_it_changes_and_not_after_unsubscribing(
    robot: Robot, client: FoxgloveClient
) -> None:
    watch = robot.server.bridge.parameters
    polls = watch.polls
    time.sleep(4 * PARAM_POLL_S)
    assert watch.polls == polls  # nobody subscribed: the graph is not polled
    client.command("subscribeParameterUpdates", names=[robot.name("gain"), robot.name("count")])
    wait_until(lambda: watch.subscribers, what="the subscription")
    robot.set("gain", 7.5)
    update = client.wait("parameterValues", lambda e: e.get("id") is None)
    assert update["parameters"] == [{"name": robot.name("gain"), "value": 7.5, "type": "float64"}]
    robot.set("count", 9)
    update = client.wait("parameterValues", lambda e: e.get("id") is None)
    assert update["parameters"] == [{"name": robot.name("count"), "value": 9}]

    client.command("unsubscribeParameterUpdates", names=[])
    wait_until(lambda: not watch.subscribers, what="the unsubscription")
    robot.set("gain", 1.5)
    with pytest.raises(AssertionError, match="no parameterValues"):
        client.wait("parameterValues", lambda e: e.get("id") is None, timeout=5 * PARAM_POLL_S)
    polls = watch.polls
    time.sleep(4 * PARAM_POLL_S)
    assert watch.polls == polls


def test_a_clients_own_change_reaches_the_other_subscribers(robot: Robot, client: FoxgloveClient) -> None:
    other = FoxgloveClient(robot.port)
    try:
        other.wait("serverInfo")
        other.command("subscribeParameterUpdates", names=[robot.name("label")])
        wait_until(lambda: robot.server.bridge.parameters.subscribers, what="the subscription")
        client.command("setParameters", parameters=[{"name": robot.name("label"), "value": "gripper"}])
        update = other.wait("parameterValues")
        assert update["parameters"] == [{"name": robot.name("label"), "value": "gripper"}]
    finally:
        other.close()
    wait_until(lambda: not robot.server.bridge.parameters.subscribers, what="the leaving client's subscription to end")


# ---------------------------------------------------------------------- bad input


BAD: list[tuple[str, Callable[[Robot], dict[str, Any]], str]] = [
    ("not an array", lambda r: {"op": "setParameters", "parameters": {"gain": 1}}, "'parameters' must be an array"),
    ("empty", lambda r: {"op": "setParameters", "parameters": []}, "'parameters' is empty"),
    ("no name", lambda r: {"op": "setParameters", "parameters": [{"value": 1}]}, "parameters[0].name must be"),
    (
        "an object value",
        lambda r: {
            "op": "setParameters",
            "parameters": [{"name": r.name("gain"), "value": 1.5}, {"name": r.name("label"), "value": {"a": 1}}],
        },
        "parameters[1].value must be a number, a boolean, a string or an array",
    ),
    (
        "a mixed array",
        lambda r: {"op": "setParameters", "parameters": [{"name": r.name("tags"), "value": ["a", 1]}]},
        "parameters[0].value must be",
    ),
    (
        "an unknown type",
        lambda r: {"op": "setParameters", "parameters": [{"name": r.name("count"), "value": 1, "type": "int64"}]},
        "parameters[0].type must be one of byte_array, float64, float64_array",
    ),
    (
        "bad base64",
        lambda r: {
            "op": "setParameters",
            "parameters": [{"name": r.name("blob"), "value": "%%", "type": "byte_array"}],
        },
        "parameters[0].value is not base64",
    ),
    (
        "a float64 that is text",
        lambda r: {"op": "setParameters", "parameters": [{"name": r.name("gain"), "value": "x", "type": "float64"}]},
        "must be a number for type float64",
    ),
    ("names not an array", lambda r: {"op": "getParameters", "parameterNames": "gain"}, "'parameterNames' must be"),
    ("a name not text", lambda r: {"op": "subscribeParameterUpdates", "parameterNames": [5]}, "'parameterNames[0]'"),
    ("an id not text", lambda r: {"op": "getParameters", "parameterNames": [], "id": 7}, "'id' must be a string"),
]
BAD_ROS2: list[tuple[str, Callable[[Robot], dict[str, Any]], str]] = [
    (
        "a wrong type",
        lambda r: {"op": "setParameters", "parameters": [{"name": r.name("count"), "value": "three"}]},
        "the node holds it as integer, not string",
    ),
    (
        "an undeclared parameter",
        lambda r: {"op": "setParameters", "parameters": [{"name": r.name("nope"), "value": 1}]},
        "no such parameter (a ROS 2 node takes only the parameters it declared)",
    ),
    (
        "a value the node refuses, after one it took",
        lambda r: {
            "op": "setParameters",
            "parameters": [{"name": r.name("gain"), "value": 9.5}, {"name": r.name("count"), "value": -1}],
        },
        "count must not be negative; nothing was changed",
    ),
    (
        "an unset the node refuses",
        lambda r: {"op": "setParameters", "parameters": [{"name": r.name("label")}]},
        "refused to delete it: Static parameter cannot be undeclared; nothing was changed",
    ),
    (
        "a name without its node",
        lambda r: {"op": "getParameters", "parameterNames": ["gain"]},
        "ROS 2 parameters belong to nodes",
    ),
]
BAD_ROS1: list[tuple[str, Callable[[Robot], dict[str, Any]], str]] = [
    (
        "an unset of a parameter that is not set",
        lambda r: {"op": "setParameters", "parameters": [{"name": r.name("never_set")}]},
        "no such parameter to unset",
    ),
]


CASES = [(ros, *case) for ros, cases in ((None, BAD), ("ros2", BAD_ROS2), ("ros1", BAD_ROS1)) for case in cases]


@pytest.mark.parametrize(("only", "case", "frame", "says"), CASES, ids=[c[1] for c in CASES])
def test_bad_parameter_input_gets_a_status_and_changes_nothing(
    only: str | None,
    case: str,
    frame: Callable[[Robot], dict[str, Any]],
    says: str,
    robot: Robot,
    client: FoxgloveClient,
) -> None:
    if only not in (None, robot.ros):
        pytest.skip(f"a {only} case")
    before = robot.values(*VALUES)
    client.command("raw", text=json.dumps(frame(robot)))
    status = client.status(says)
    assert status["level"] == 2
    assert robot.values(*VALUES) == before
    client.command("getParameters", names=[robot.name("gain")], id="after")  # the connection keeps working
    assert client.wait("parameterValues", lambda e: e["id"] == "after")["parameters"][0]["value"] == before["gain"]


# ---------------------------------------------------------------------- simulated time


@dataclass
class SimRobot:
    server: FoxgloveServer
    loop: LoopThread


def _ros1_sim_robot(home: Path, loop: LoopThread) -> Iterator[SimRobot]:
    from bridgeos_agent.bridges.ros1graph import Ros1Graph

    with private_rosmaster(home) as master:
        xmlrpc.client.ServerProxy(master).setParam("/test", "/use_sim_time", True)

        async def start() -> tuple[FoxgloveServer, Ros1Graph, asyncio.Task[None]]:
            simulator = Ros1Graph(master, name="/simulator")  # another node of the graph, publishing /clock
            await simulator.start()
            clock = await simulator.advertise("/clock", "rosgraph_msgs/Clock")

            async def tick() -> None:
                nanoseconds = 1000 * 10**9
                while True:
                    nanoseconds += 10**7
                    clock.publish({"clock": {"secs": nanoseconds // 10**9, "nsecs": nanoseconds % 10**9}})
                    await asyncio.sleep(0.01)

            ticking = asyncio.get_running_loop().create_task(tick())
            graph = Ros1Graph(master, name="/bridgeos_foxglove")
            await graph.start()
            server = FoxgloveServer(graph, poll_s=0.5)
            await server.start("127.0.0.1", 0)
            return server, simulator, ticking

        server, simulator, ticking = loop.run(start())
        nodes = Nodes(master, home)
        nodes.run("talker", "talker", "--topic", "/chatter", "--rate", "20", "--tag", "sim")
        try:
            yield SimRobot(server, loop)
        finally:
            nodes.kill_all()

            async def stop() -> None:
                ticking.cancel()
                await server.close()
                await simulator.close()

            loop.run(stop())


def _ros2_sim_robot(home: Path, loop: LoopThread) -> Iterator[SimRobot]:
    from bridgeos_agent.bridges.ros2graph import Ros2BridgeGraph

    # A domain of this run's own: a /clock here must not put anyone else's graph on simulated time.
    graph = Ros2Graph(domain_id=100 + os.getpid() % 100, discovery_range="LOCALHOST")
    nodes = Ros2Nodes(graph, home)
    run_action_server(nodes, "clock", "--clock")
    nodes.run("talker", "talker", "--topic", "/chatter", "--rate", "20", "--tag", "sim", "--linger", "0")

    async def start() -> FoxgloveServer:
        server = FoxgloveServer(Ros2BridgeGraph(graph, asyncio.get_running_loop(), name="bridgeos_sim"), poll_s=0.5)
        await server.start("127.0.0.1", 0)
        return server

    server = loop.run(start())
    try:
        wait_until(lambda: loop.run(server.graph.simulated_clock()), timeout=20, what="/clock in the graph")
        yield SimRobot(server, loop)
    finally:
        loop.run(server.close())
        nodes.kill_all()


@pytest.fixture(params=["ros1", "ros2"])
def sim_robot(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[SimRobot]:
    loop = LoopThread()
    try:
        if request.param == "ros1":
            if not ros1_available():
                pytest.skip("Debian's ROS 1 (rospy, rosmaster) is not installed")
            yield from _ros1_sim_robot(tmp_path, loop)
        else:
            if rclpy_missing() is not None:
                pytest.skip("rclpy is not installed")
            yield from _ros2_sim_robot(tmp_path, loop)
    finally:
        loop.stop()


def test_on_simulated_time_the_server_tells_the_time_and_stamps_messages_with_it(sim_robot: SimRobot) -> None:
    client = FoxgloveClient(sim_robot.server.port)
    try:
        assert "time" in client.wait("serverInfo")["info"]["capabilities"]
        stamps = [int(client.wait("time")["timestamp"]) for _ in range(5)]
        assert all(1000 * 10**9 < stamp < 2000 * 10**9 for stamp in stamps)  # the simulator's, not the wall's
        assert stamps == sorted(stamps) and stamps[-1] > stamps[0]
        client.channel("/chatter", timeout=20)
        client.command("subscribe", topic="/chatter")
        client.wait("subscribed")
        message = client.wait("message", timeout=20)
        assert 1000 * 10**9 < int(message["timestamp"]) < 2000 * 10**9
    finally:
        client.close()
