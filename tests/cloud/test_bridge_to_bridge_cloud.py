"""Bridge clients of one robot hear each other through the cloud, and a recording keeps what they publish.

Two roslibpy clients on ``/ws/rosbridge/<robot>/`` and one @foxglove/ws-protocol client on
``/ws/foxglove/<robot>/`` (a daphne of this module's own, a real agent connected to it, real rospy
or rclpy nodes): whatever one client publishes, every subscriber hears exactly once, the
publisher's own subscription and the robot's ROS nodes included, and an MCAP recording of the
topic holds every message.
"""

from __future__ import annotations

import io
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import roslibpy
from mcap.reader import make_reader

from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.ros2graph import rclpy_missing
from robots.models import Robot
from tests.agent.bridgeclients import FoxgloveSide, RosbridgeSide
from tests.agent.foxgloveclient import FoxgloveClient, node_client_ready
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.agent.roshelpers import HOST_PYTHON, Nodes, private_rosmaster
from tests.agent.test_bridge_to_bridge import COUNT, STRING_SCHEMA, node_texts, publish_to_everyone, seqs
from tests.cloud.test_bridge_relay import make_robot, ticket
from tests.conftest import LoopThread, Server, another_daphne, wait_until

pytestmark = [pytest.mark.ros, pytest.mark.django_db(transaction=True), pytest.mark.timeout(180)]

TOPIC = "/probe_cloud"


@pytest.fixture(scope="module")
def cloud(django_db_setup, django_db_blocker, tmp_path_factory) -> Iterator[Server]:
    log = tmp_path_factory.mktemp("b2b-cloud") / "daphne.log"
    with another_daphne(log, BRIDGEOS_RECORDINGS_DIR=str(log.parent / "recordings")) as (server, _):
        yield server


@dataclass
class Bot:
    id: str
    ros: str
    api_token: str
    nodes: Nodes | Ros2Nodes

    def node_heard(self, key: str) -> list[tuple[str, int]]:
        return self.nodes.messages(key)


@pytest.fixture(params=["ros1", "ros2"])
def robot(
    request: pytest.FixtureRequest, cloud: Server, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> Iterator[Bot]:
    ros = request.param
    if not node_client_ready():
        pytest.skip("the @foxglove/ws-protocol client is not installed (scripts/services.sh node)")
    robot_id = f"b2b-{ros}"
    if ros == "ros1":
        if not (Path(HOST_PYTHON).exists() and Path("/usr/bin/rosmaster").exists()):
            pytest.skip("Debian's ROS 1 (rospy, rosmaster) is not installed")
        with private_rosmaster(tmp_path) as master:
            monkeypatch.setenv("ROS_MASTER_URI", master)
            nodes = Nodes(master, tmp_path)
            nodes.run(TOPIC, "listener", "--topic", TOPIC)
            try:
                yield from _agent(robot_id, ros, cloud, tmp_path, nodes, {})
            finally:
                nodes.kill_all()
    else:
        if rclpy_missing() is not None:
            pytest.skip("rclpy is not installed")
        graph = loopback_graph()
        for name, value in graph.env().items():
            monkeypatch.setenv(name, value)
        monkeypatch.delenv("ROS_MASTER_URI", raising=False)
        nodes2 = Ros2Nodes(graph, tmp_path)
        nodes2.run(TOPIC, "listener", "--topic", TOPIC)
        try:
            yield from _agent(robot_id, ros, cloud, tmp_path, nodes2, {"ros2": "on", "detect_ros_master": False})
        finally:
            nodes2.kill_all()


def _agent(robot_id: str, ros: str, cloud: Server, home: Path, nodes: Any, options: dict[str, Any]) -> Iterator[Bot]:
    token, api_token = make_robot(robot_id)
    settings = AgentSettings(
        master=cloud.ws_url,
        robot=robot_id,
        token=token,
        data_dir=home / "agent",
        simulate=True,
        reconnect_initial=0.2,
        **options,
    )
    loop = LoopThread()
    controller = loop.call(lambda: RobotController(settings, plugins={}))
    running = loop.start(controller.run())
    try:
        wait_until(
            lambda: Robot.objects.filter(id=robot_id, connected=True).exists(), timeout=20, what="the robot connected"
        )
        wait_until(lambda: "ready" in nodes.lines(TOPIC), timeout=20, what="the ROS listener")
        yield Bot(robot_id, ros, api_token, nodes)
    finally:
        loop.loop.call_soon_threadsafe(controller.stop)
        running.result(30)
        loop.stop()
        # The cloud records the departure before the test's data is flushed away (else they deadlock).
        wait_until(
            lambda: not Robot.objects.filter(connected=True).exists(), timeout=20, what="the robot recorded offline"
        )


def rosbridge_client(cloud: Server, bot: Bot, name: str) -> RosbridgeSide:
    ros = roslibpy.Ros(f"{cloud.ws_url}/ws/rosbridge/{bot.id}/", headers={"Authorization": f"Token {bot.api_token}"})
    ros.run(timeout=10)
    return RosbridgeSide(ros, name)


def foxglove_client(cloud: Server, bot: Bot) -> FoxgloveSide:
    client = FoxgloveClient(ticket(cloud, bot.id, bot.api_token)["foxglove_url"])
    client.wait("serverInfo")
    return FoxgloveSide(client, "viewer", bot.ros)


def recorded(cloud: Server, bot: Bot, recording: str) -> list[str]:
    """Stop a recording, download its MCAP file and return the texts of its messages."""
    headers = {"Authorization": f"Token {bot.api_token}"}
    base = f"{cloud.url}/api/robot/{bot.id}/recordings/{recording}"
    stopped = httpx.post(f"{base}/stop?wait=15", headers=headers, timeout=30)
    assert stopped.status_code in (200, 202), stopped.text

    def done() -> dict[str, Any] | None:
        answer = httpx.get(base, headers=headers, timeout=10).json()
        return answer if answer["status"] in ("finished", "failed") else None

    assert wait_until(done, timeout=30, what="the recording assembled")["status"] == "finished"
    data = httpx.get(f"{base}/download", headers=headers, timeout=30).content
    if bot.ros == "ros1":
        from mcap_ros1.decoder import DecoderFactory
    else:
        from mcap_ros2.decoder import DecoderFactory
    reader = make_reader(io.BytesIO(data), decoder_factories=[DecoderFactory()])
    return [message.data for _, _, _, message in reader.iter_decoded_messages()]


def start_recording(cloud: Server, bot: Bot) -> str:
    headers = {"Authorization": f"Token {bot.api_token}"}
    deadline = time.monotonic() + 30
    while True:
        answer = httpx.post(
            f"{cloud.url}/api/robot/{bot.id}/recordings?wait=15",
            json={"topics": [TOPIC], "ros": bot.ros},
            headers=headers,
            timeout=30,
        )
        if answer.status_code == 201:
            return answer.json()["id"]
        assert answer.status_code == 400 and "unknown topic" in answer.text, answer.text
        assert time.monotonic() < deadline, answer.text
        time.sleep(0.2)


def test_clients_through_the_cloud_hear_each_other_once_and_the_recording_keeps_it_all(cloud, robot: Bot) -> None:
    first, second, viewer = (
        rosbridge_client(cloud, robot, "first"),
        rosbridge_client(cloud, robot, "second"),
        foxglove_client(cloud, robot),
    )
    try:
        first.advertise(TOPIC)
        first.subscribe(TOPIC)
        second.subscribe(TOPIC)
        viewer.subscribe(TOPIC)
        recording = start_recording(cloud, robot)
        publish_to_everyone(
            first,
            TOPIC,
            {
                "the publishing client": lambda: first.heard(TOPIC),
                "another rosbridge client": lambda: second.heard(TOPIC),
                "a Foxglove client": lambda: viewer.heard(TOPIC),
                "a ROS node": node_texts(robot, TOPIC),
            },
        )
        # And the other way: the Foxglove client publishes, the rosbridge clients hear it once.
        viewer.advertise(TOPIC, STRING_SCHEMA)
        sent = 0

        def heard_viewer() -> bool:
            nonlocal sent
            sent += 1
            viewer.publish(TOPIC, f"fox {sent} {time.time():.6f}")
            return bool(seqs(first.heard(TOPIC), "fox") and seqs(second.heard(TOPIC), "fox"))

        wait_until(heard_viewer, timeout=30, what="the rosbridge clients to hear the Foxglove client")
        texts = recorded(cloud, robot, recording)
        assert sorted(set(seqs(texts, "probe"))) == list(range(1, COUNT + 1))
        assert len(seqs(texts, "probe")) == COUNT  # recorded once each
        assert seqs(texts, "fox")
    finally:
        for client in (first, second, viewer):
            client.close()
