"""Bridge clients on one robot hear each other, as they do through rosbridge_server and rospy.

Two roslibpy clients and one @foxglove/ws-protocol client on a robot's local doors (a rosbridge
door and a Foxglove door, each its own node of the graph, as ``bridgeos-agent run --rosbridge
--foxglove`` serves them), with a rospy or rclpy node beside them: whatever one of them publishes,
every subscriber of the topic hears exactly once, the publisher's own subscription included.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import roslibpy

from bridgeos_agent.bridges.server import FoxgloveServer, RosbridgeServer
from bridgeos_agent.ros2graph import rclpy_missing
from tests.agent.bridgeclients import FoxgloveSide, RosbridgeSide, text
from tests.agent.foxgloveclient import FoxgloveClient, node_client_ready
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.agent.roshelpers import HOST_PYTHON, Nodes, private_rosmaster
from tests.conftest import LoopThread, wait_until

pytestmark = [pytest.mark.timeout(180)]

COUNT = 50  # numbered messages per case, after the warm-up
STRING_SCHEMA = "string data\n"


@dataclass
class Robot:
    ros: str
    rosbridge: RosbridgeServer
    foxglove: FoxgloveServer
    nodes: Nodes | Ros2Nodes
    loop: LoopThread

    def node_heard(self, key: str) -> list[tuple[str, int]]:
        return self.nodes.messages(key)


@pytest.fixture(scope="module", params=["ros1", "ros2"])
def robot(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    ros = request.param
    if not node_client_ready():
        pytest.skip("the @foxglove/ws-protocol client is not installed (scripts/services.sh node)")
    home = tmp_path_factory.mktemp(f"b2b-{ros}")
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


LISTENED = ("/probe_rosbridge", "/probe_foxglove")  # a ROS node listens to each case's topic


def _ros1_robot(home: Path, loop: LoopThread) -> Iterator[Robot]:
    from bridgeos_agent.bridges.ros1graph import Ros1Graph

    with private_rosmaster(home) as master:
        nodes = Nodes(master, home)
        for topic in LISTENED:
            nodes.run(topic, "listener", "--topic", topic)

        async def start() -> tuple[RosbridgeServer, FoxgloveServer]:
            # Two nodes, as the agent's two doors are.
            rosbridge_graph = Ros1Graph(master, name="/bridgeos_rosbridge")
            foxglove_graph = Ros1Graph(master, name="/bridgeos_foxglove")
            await rosbridge_graph.start()
            await foxglove_graph.start()
            rosbridge = RosbridgeServer(rosbridge_graph, linger_s=0.5)
            foxglove = FoxgloveServer(foxglove_graph, linger_s=0.5, poll_s=0.3)
            await rosbridge.start("127.0.0.1", 0)
            await foxglove.start("127.0.0.1", 0)
            return rosbridge, foxglove

        rosbridge, foxglove = loop.run(start())
        try:
            wait_until(lambda: all("ready" in nodes.lines(t) for t in LISTENED), timeout=20, what="the ROS listeners")
            yield Robot("ros1", rosbridge, foxglove, nodes, loop)
        finally:
            loop.run(rosbridge.close())
            loop.run(foxglove.close())
            nodes.kill_all()


def _ros2_robot(home: Path, loop: LoopThread) -> Iterator[Robot]:
    from bridgeos_agent.bridges.ros2graph import Ros2BridgeGraph

    graph = loopback_graph()
    nodes = Ros2Nodes(graph, home)
    for topic in LISTENED:
        nodes.run(topic, "listener", "--topic", topic)

    async def start() -> tuple[RosbridgeServer, FoxgloveServer]:
        running = asyncio.get_running_loop()
        rosbridge = RosbridgeServer(Ros2BridgeGraph(graph, running, name="bridgeos_rosbridge"), linger_s=0.5)
        foxglove = FoxgloveServer(Ros2BridgeGraph(graph, running, name="bridgeos_foxglove"), linger_s=0.5, poll_s=0.3)
        await rosbridge.start("127.0.0.1", 0)
        await foxglove.start("127.0.0.1", 0)
        return rosbridge, foxglove

    rosbridge, foxglove = loop.run(start())
    try:
        wait_until(lambda: all("ready" in nodes.lines(t) for t in LISTENED), timeout=20, what="the ROS listeners")
        yield Robot("ros2", rosbridge, foxglove, nodes, loop)
    finally:
        loop.run(rosbridge.close())
        loop.run(foxglove.close())
        nodes.kill_all()


@pytest.fixture
def clients(robot: Robot) -> Iterator[tuple[RosbridgeSide, RosbridgeSide, FoxgloveSide]]:
    opened: list[RosbridgeSide | FoxgloveSide] = []
    try:
        for name in ("first", "second"):
            ros = roslibpy.Ros("127.0.0.1", robot.rosbridge.port)
            ros.run(timeout=10)
            opened.append(RosbridgeSide(ros, name))
        viewer = FoxgloveClient(robot.foxglove.port)
        viewer.wait("open")
        opened.append(FoxgloveSide(viewer, "viewer", robot.ros))
        yield opened[0], opened[1], opened[2]  # type: ignore[misc]
    finally:
        for client in opened:
            client.close()


def seqs(texts: list[str], tag: str) -> list[int]:
    return [int(t.split()[1]) for t in texts if t.startswith(tag + " ")]


def exactly_once(heard: dict[str, list[int]]) -> dict[str, str]:
    """Return, per subscriber, what is wrong with what it heard of 1..COUNT (empty when nothing)."""
    wrong = {}
    for who, got in heard.items():
        counts = Counter(got)
        missing = sorted(set(range(1, COUNT + 1)) - set(counts))
        twice = sorted(seq for seq, n in counts.items() if n > 1)
        if missing or twice:
            wrong[who] = f"missing {missing[:10]}{'...' if len(missing) > 10 else ''}, more than once {twice[:10]}"
    return wrong


def publish_to_everyone(publisher, topic: str, hearers: dict[str, Callable[[], list[str]]]) -> None:
    """Warm the topic up until every hearer has heard it, then send COUNT numbered messages."""
    sent = 0

    def all_warm() -> bool:
        nonlocal sent
        sent += 1
        publisher.publish(topic, text("warm", sent))
        return all(seqs(hear(), "warm") for hear in hearers.values())

    try:
        wait_until(all_warm, timeout=45, what=f"every subscriber of {topic} to hear the warm-up")
    except AssertionError:
        cold = [who for who, hear in hearers.items() if not seqs(hear(), "warm")]
        raise AssertionError(f"{', '.join(cold)} never heard {topic} ({sent} messages sent)") from None
    for seq in range(1, COUNT + 1):
        publisher.publish(topic, text("probe", seq))

    def everyone_has_all() -> bool:
        return all(len(set(seqs(hear(), "probe"))) >= COUNT for hear in hearers.values())

    try:
        wait_until(everyone_has_all, timeout=20, what="every subscriber to hear every message")
    finally:
        time.sleep(0.5)  # a duplicate would arrive by now
        heard = {who: seqs(hear(), "probe") for who, hear in hearers.items()}
        assert exactly_once(heard) == {}, heard


def node_texts(robot: Robot | Any, key: str) -> Callable[[], list[str]]:
    return lambda: [f"{tag} {seq} 0" for tag, seq in robot.node_heard(key)]


def test_a_rosbridge_clients_message_reaches_itself_the_other_clients_and_ros_once(robot: Robot, clients) -> None:
    first, second, viewer = clients
    topic = "/probe_rosbridge"
    first.advertise(topic)
    first.subscribe(topic)  # the publisher's own subscription, on the same connection
    second.subscribe(topic)
    viewer.subscribe(topic)
    publish_to_everyone(
        first,
        topic,
        {
            "the publishing client": lambda: first.heard(topic),
            "another rosbridge client": lambda: second.heard(topic),
            "a Foxglove client": lambda: viewer.heard(topic),
            "a ROS node": node_texts(robot, topic),
        },
    )


def test_a_foxglove_clients_message_reaches_itself_rosbridge_clients_and_ros_once(robot: Robot, clients) -> None:
    first, second, viewer = clients
    topic = "/probe_foxglove"
    viewer.advertise(topic, STRING_SCHEMA)
    first.subscribe(topic)
    second.subscribe(topic)
    viewer.subscribe(topic)  # its own publication, as foxglove_bridge delivers it through the graph
    publish_to_everyone(
        viewer,
        topic,
        {
            "a rosbridge client": lambda: first.heard(topic),
            "another rosbridge client": lambda: second.heard(topic),
            "the publishing Foxglove client": lambda: viewer.heard(topic),
            "a ROS node": node_texts(robot, topic),
        },
    )


def test_a_ros_nodes_message_reaches_every_bridge_client_once(robot: Robot, clients) -> None:
    first, second, viewer = clients
    topic = "/probe_node"
    robot.nodes.run("talker", "talker", "--topic", topic, "--rate", "50", "--tag", "probe", "--linger", "0")
    first.subscribe(topic)
    second.subscribe(topic)
    viewer.subscribe(topic)
    hearers = {"first": first, "second": second, "viewer": viewer}
    wait_until(lambda: all(len(seqs(c.heard(topic), "probe")) >= 100 for c in hearers.values()), timeout=30)
    for who, client in hearers.items():
        got = seqs(client.heard(topic), "probe")
        # Each joined at some point of the talker's run; from then on, every message once, in order.
        assert got == list(range(got[0], got[0] + len(got))), (who, got[:20])
