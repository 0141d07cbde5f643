"""ROS 2 actions through the cloud: roslibpy's ActionClient → daphne → a real agent → a real rclpy action server.

The cloud passes rosbridge frames through unread, so send_action_goal, cancel_action_goal and the
robot's action_feedback and action_result cross it as any other frame; the clients and the cloud are
those of test_bridge_relay, the robot's ROS 2 graph that of test_bridge_relay_ros2.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import roslibpy
from roslibpy.core import GoalStatus

from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.ros2graph import rclpy_missing
from robots.models import Robot
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.agent.test_rosbridge_actions import FIBONACCI, run_action_server
from tests.cloud.test_bridge_relay import Bot, cloud, make_robot, raw, token_client, url
from tests.conftest import LoopThread, Server, wait_until

pytestmark = [
    pytest.mark.ros,
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(120),
    pytest.mark.skipif(bool(rclpy_missing()), reason="needs rclpy"),
]
__all__ = ["cloud"]  # the module's daphne, shared with test_bridge_relay's fixture

ACTION = f"/relay_fibonacci_{os.getpid()}"


@pytest.fixture
def ros2_robot(cloud: Server, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[Bot, Ros2Nodes]]:
    graph = loopback_graph()
    for name, value in graph.env().items():
        monkeypatch.setenv(name, value)
    monkeypatch.delenv("ROS_MASTER_URI", raising=False)
    nodes = Ros2Nodes(graph, tmp_path)
    run_action_server(nodes, "fibonacci", "--action", ACTION, "--step", "0.05")
    token, api_token = make_robot("bra-1")
    settings = AgentSettings(
        master=cloud.ws_url,
        robot="bra-1",
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
        wait_until(lambda: Robot.objects.filter(id="bra-1", connected=True).exists(), what="the robot connected")
        wait_until(lambda: "ready" in nodes.lines("fibonacci"), what="the ROS 2 action server")
        yield Bot("bra-1", api_token, controller, loop), nodes
    finally:
        loop.loop.call_soon_threadsafe(controller.stop)
        running.result(30)
        loop.stop()
        nodes.kill_all()


class Outcome:
    def __init__(self) -> None:
        self.feedback: list[dict[str, Any]] = []
        self.result: dict[str, Any] | None = None
        self.error: dict[str, Any] | None = None

    def callbacks(self) -> tuple[Any, Any, Any]:
        def result(value: Any) -> None:
            self.result = dict(value)

        def error(value: Any) -> None:
            self.error = dict(value)

        return result, lambda value: self.feedback.append(dict(value)), error


def test_roslibpys_action_client_reaches_a_ros2_action_server_through_the_cloud(cloud, ros2_robot) -> None:
    bot, nodes = ros2_robot
    client = token_client(cloud, bot)
    try:
        servers = roslibpy.Service(client, "/rosapi/action_servers", "rosapi/GetActionServers")
        wait_until(
            lambda: ACTION in servers.call(roslibpy.ServiceRequest({}), timeout=15)["action_servers"],
            timeout=20,
            what="the action server in /rosapi/action_servers",
        )
        action = roslibpy.ActionClient(client, ACTION, FIBONACCI)

        done = Outcome()
        goal_id = action.send_goal(roslibpy.Goal({"order": 7}), *done.callbacks())
        action.wait_goal(goal_id, timeout=30)
        assert done.error is None and done.result is not None
        assert done.result["status"] == GoalStatus.SUCCEEDED
        assert done.result["values"] == {"sequence": [0, 1, 1, 2, 3, 5, 8, 13, 21]}
        assert done.feedback and done.feedback[-1] == done.result["values"]

        cancelled = Outcome()
        goal_id = action.send_goal(roslibpy.Goal({"order": 40}), *cancelled.callbacks())
        wait_until(lambda: cancelled.feedback, what="feedback of the long goal")
        action.cancel_goal(goal_id)
        action.wait_goal(goal_id, timeout=30)
        assert cancelled.result is not None and cancelled.result["status"] == GoalStatus.CANCELED
        assert "canceled 40" in nodes.lines("fibonacci")

        missing = Outcome()
        nobody = roslibpy.ActionClient(client, "/nobody_serves_this", FIBONACCI)
        goal_id = nobody.send_goal(roslibpy.Goal({"order": 1}), *missing.callbacks())
        nobody.wait_goal(goal_id, timeout=30)
        assert missing.error == {"status": GoalStatus.UNKNOWN, "values": "no action server answers /nobody_serves_this"}
    finally:
        client.close()


def test_a_bad_action_op_through_the_cloud_gets_the_robots_status(cloud, ros2_robot) -> None:
    bot, _ = ros2_robot
    with raw(url(cloud, bot.id), additional_headers={"Authorization": f"Token {bot.api_token}"}) as websocket:
        goal = {"op": "send_action_goal", "id": "bad", "action": ACTION, "action_type": FIBONACCI, "args": {"ordr": 1}}
        websocket.send(json.dumps(goal))
        while True:
            answer = json.loads(websocket.recv(timeout=15))
            if answer["op"] == "status":
                break
        assert answer["id"] == "bad" and "no field 'ordr'" in answer["msg"]
        websocket.send(json.dumps({"op": "cancel_action_goal", "action": ACTION}))
        while True:
            answer = json.loads(websocket.recv(timeout=15))
            if answer["op"] == "status":
                break
        assert answer["msg"] == "cancel_action_goal: 'id' is missing"
