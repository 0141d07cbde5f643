"""rosbridge through the cloud on a robot whose graph is ROS 2: roslibpy → daphne → a real agent → real rclpy nodes.

The agent finds no ROS master, so the relay joins the robot's ROS 2 graph (loopback discovery, the
run's own domain); the clients and the cloud are those of test_bridge_relay.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import roslibpy

from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.ros2graph import rclpy_missing
from robots.models import Robot
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.cloud.test_bridge_relay import Bot, cloud, make_robot, token_client
from tests.conftest import LoopThread, Server, wait_until

pytestmark = [
    pytest.mark.ros,
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(120),
    pytest.mark.skipif(bool(rclpy_missing()), reason="needs rclpy"),
]
__all__ = ["cloud"]  # the module's daphne, shared with test_bridge_relay's fixture

TOPIC = f"/relay_chatter_{os.getpid()}"
SERVICE = f"/relay_trigger_{os.getpid()}"


@pytest.fixture
def ros2_robot(cloud: Server, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Bot, Ros2Nodes]]:
    graph = loopback_graph()
    for name, value in graph.env().items():
        monkeypatch.setenv(name, value)
    monkeypatch.delenv("ROS_MASTER_URI", raising=False)
    nodes = Ros2Nodes(graph, tmp_path)
    nodes.run("talker", "talker", "--topic", TOPIC, "--rate", "20", "--tag", "ros2", "--linger", "0")
    nodes.run("server", "server", "--topic", SERVICE, "--tag", "ros2_robot")
    token, api_token = make_robot("br2-1")
    settings = AgentSettings(
        master=cloud.ws_url,
        robot="br2-1",
        token=token,
        data_dir=tmp_path / "agent",
        simulate=True,
        reconnect_initial=0.2,
        ros2="on",
        detect_ros_master=False,
    )
    loop = LoopThread()
    controller = loop.call(lambda: RobotController(settings, plugins={}))
    running = loop.start(controller.run())
    try:
        wait_until(lambda: Robot.objects.filter(id="br2-1", connected=True).exists(), what="the robot connected")
        wait_until(lambda: "ready" in nodes.lines("server"), what="the ROS 2 service server")
        yield Bot("br2-1", api_token, controller, loop), nodes
    finally:
        loop.loop.call_soon_threadsafe(controller.stop)
        running.result(30)
        loop.stop()
        nodes.kill_all()
        # Its disconnect written before the tables are flushed: the two deadlock otherwise.
        wait_until(lambda: not Robot.objects.filter(connected=True).exists(), what="the robot recorded offline")


def test_roslibpy_subscribes_and_calls_a_service_of_a_ros2_robot_through_the_cloud(cloud, ros2_robot) -> None:
    bot, _ = ros2_robot
    client = token_client(cloud, bot)
    try:
        # The ROS 2 graph discovers the talker a moment after it joins: the topic list says when.
        wait_until(lambda: TOPIC in client.get_topics(), timeout=20, what="the ROS 2 talker in /rosapi/topics")
        assert client.get_topic_type(TOPIC) == "std_msgs/msg/String"
        heard: list[dict[str, Any]] = []
        chatter = roslibpy.Topic(client, TOPIC, "std_msgs/msg/String")
        chatter.subscribe(heard.append)
        wait_until(lambda: len(heard) >= 5, what="the ROS 2 talker through the cloud")
        assert all(message["data"].startswith("ros2 ") for message in heard)
        assert bot.controller.bridges.graph is not None
        assert type(bot.controller.bridges.graph).__name__ == "Ros2BridgeGraph"

        wait_until(lambda: SERVICE in client.get_services(), timeout=20, what="the ROS 2 service in /rosapi/services")
        trigger = roslibpy.Service(client, SERVICE, "std_srvs/srv/Trigger")
        assert trigger.call(roslibpy.ServiceRequest({}), timeout=15) == {"success": True, "message": "ros2_robot"}
        chatter.unsubscribe()
        wait_until(lambda: TOPIC not in bot.engine().subscribed_topics(), what="the robot to leave the topic")
    finally:
        client.close()
