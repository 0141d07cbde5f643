"""rosbridge v2's action ops on the robot's door: roslibpy's own ActionClient against a real rclpy action server."""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import roslibpy
from roslibpy.core import GoalStatus
from websockets.sync.client import ClientConnection, connect

from bridgeos_agent.bridges.server import RosbridgeServer
from bridgeos_agent.ros2graph import rclpy_missing
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.agent.roshelpers import private_rosmaster
from tests.agent.test_rosbridge import ask, ros1_available
from tests.conftest import LoopThread, wait_until

pytestmark = [pytest.mark.timeout(120)]

ACTION_NODES = str(Path(__file__).with_name("ros2actionnodes.py"))
ACTION = f"/fibonacci_{os.getpid()}"
FIBONACCI = "test_msgs/action/Fibonacci"


def run_action_server(nodes: Ros2Nodes, key: str, *args: str) -> None:
    """Start tests/agent/ros2actionnodes.py in the nodes' graph; its output is read with ``nodes.lines(key)``."""
    env = {**os.environ, **nodes.graph.env(), "PYTHONUNBUFFERED": "1"}
    env.pop("ROS_DISCOVERY_SERVER", None)
    out = (nodes.directory / f"{key}.out").open("wb")
    command = [sys.executable, ACTION_NODES, *args]
    nodes.processes[key] = subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT)


@dataclass
class Robot:
    server: RosbridgeServer
    loop: LoopThread
    nodes: Ros2Nodes

    @property
    def port(self) -> int:
        return self.server.port

    def known_actions(self) -> dict[str, list[str]]:
        """Return the actions the bridge's node sees in the graph (servers' and clients')."""
        graph: Any = self.server.graph
        return graph.actions.known()


@pytest.fixture(scope="module")
def robot(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Robot]:
    if rclpy_missing() is not None:
        pytest.skip("rclpy is not installed")
    from bridgeos_agent.bridges.ros2graph import Ros2BridgeGraph

    graph = loopback_graph()
    nodes = Ros2Nodes(graph, tmp_path_factory.mktemp("actions"))
    run_action_server(nodes, "fibonacci", "--action", ACTION, "--step", "0.05", "--abort-at", "20")
    loop = LoopThread()

    async def start() -> RosbridgeServer:
        server = RosbridgeServer(Ros2BridgeGraph(graph, asyncio.get_running_loop()))
        await server.start("127.0.0.1", 0)
        return server

    server = loop.run(start())
    try:
        wait_until(lambda: "ready" in nodes.lines("fibonacci"), what="the action server")
        robot = Robot(server, loop, nodes)
        wait_until(lambda: ACTION in robot.known_actions(), timeout=20, what="the action server in the graph")
        yield robot
    finally:
        loop.run(server.close())
        loop.stop()
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


class Outcome:
    """What roslibpy's ActionClient hands its three callbacks for one goal."""

    def __init__(self) -> None:
        self.feedback: list[dict[str, Any]] = []
        self.result: dict[str, Any] | None = None
        self.error: dict[str, Any] | None = None
        self.done = threading.Event()

    def on_result(self, result: dict[str, Any]) -> None:
        self.result = dict(result)
        self.done.set()

    def on_feedback(self, feedback: dict[str, Any]) -> None:
        self.feedback.append(dict(feedback))

    def on_error(self, error: dict[str, Any]) -> None:
        self.error = dict(error)
        self.done.set()


def send(action: roslibpy.ActionClient, order: int) -> tuple[str, Outcome]:
    outcome = Outcome()
    goal_id = action.send_goal(
        roslibpy.Goal({"order": order}), outcome.on_result, outcome.on_feedback, outcome.on_error
    )
    return goal_id, outcome


# ---------------------------------------------------------------------- roslibpy's ActionClient


def test_a_goal_reports_its_feedback_and_succeeds_with_the_result(robot: Robot, client: roslibpy.Ros) -> None:
    action = roslibpy.ActionClient(client, ACTION, FIBONACCI)
    goal_id, outcome = send(action, 6)
    action.wait_goal(goal_id, timeout=30)
    assert outcome.error is None and outcome.result is not None
    assert outcome.result["status"] == GoalStatus.SUCCEEDED
    assert outcome.result["values"] == {"sequence": [0, 1, 1, 2, 3, 5, 8, 13]}
    # Each feedback is the sequence so far (the very first may be missed while a new action client's
    # feedback subscription is still being discovered, as with any rclpy action client).
    full = [0, 1, 1, 2, 3, 5, 8, 13]
    assert outcome.feedback and outcome.feedback[-1] == {"sequence": full}
    assert all(f["sequence"] == full[: len(f["sequence"])] for f in outcome.feedback)


def test_a_cancelled_goal_ends_with_status_canceled(robot: Robot, client: roslibpy.Ros) -> None:
    action = roslibpy.ActionClient(client, ACTION, FIBONACCI)
    goal_id, outcome = send(action, 19)  # about a second of work
    wait_until(lambda: outcome.feedback, what="the first feedback")
    action.cancel_goal(goal_id)
    action.wait_goal(goal_id, timeout=30)
    assert outcome.result is not None and outcome.result["status"] == GoalStatus.CANCELED
    assert len(outcome.result["values"]["sequence"]) < 19 + 2
    assert "canceled 19" in robot.nodes.lines("fibonacci")


def test_an_aborted_goal_ends_with_status_aborted(robot: Robot, client: roslibpy.Ros) -> None:
    action = roslibpy.ActionClient(client, ACTION, FIBONACCI)
    goal_id, outcome = send(action, 20)  # --abort-at 20: the server gives up half-way
    action.wait_goal(goal_id, timeout=30)
    assert outcome.result is not None and outcome.result["status"] == GoalStatus.ABORTED


def test_a_rejected_goal_reaches_the_errback_with_the_reason(robot: Robot, client: roslibpy.Ros) -> None:
    action = roslibpy.ActionClient(client, ACTION, FIBONACCI)
    goal_id, outcome = send(action, -1)
    action.wait_goal(goal_id, timeout=30)
    assert outcome.result is None and outcome.error is not None
    assert outcome.error["status"] == GoalStatus.UNKNOWN
    assert outcome.error["values"] == f"{ACTION} rejected the goal"


def test_goals_run_side_by_side_and_each_gets_its_own_answers(robot: Robot, client: roslibpy.Ros) -> None:
    action = roslibpy.ActionClient(client, ACTION, FIBONACCI)
    sent = [send(action, order) for order in (3, 5, 4)]
    for goal_id, _ in sent:
        action.wait_goal(goal_id, timeout=30)
    lengths = [len(outcome.result["values"]["sequence"]) for _, outcome in sent if outcome.result is not None]
    assert lengths == [5, 7, 6]
    assert all(outcome.feedback[-1] == outcome.result["values"] for _, outcome in sent if outcome.result)


def test_a_goal_to_a_missing_action_server_fails_clearly_and_leaves_the_graph_as_it_was(
    robot: Robot, client: roslibpy.Ros, raw: ClientConnection
) -> None:
    missing = f"/nobody_serves_{os.getpid()}"
    action = roslibpy.ActionClient(client, missing, FIBONACCI)
    goal_id, outcome = send(action, 3)
    action.wait_goal(goal_id, timeout=30)
    assert outcome.error == {"status": GoalStatus.UNKNOWN, "values": f"no action server answers {missing}"}

    goal = {"op": "send_action_goal", "id": "g-missing", "action": missing, "action_type": FIBONACCI, "args": {}}
    # The result alone says why, as rosbridge_server's does: a status beside it would be logged as an
    # error by roslibpy, which has no handler for status.
    result = ask(raw, goal, op="action_result")
    assert (result["id"], result["result"], result["status"]) == ("g-missing", False, 0)
    assert result["values"] == f"no action server answers {missing}"
    # No action client of the bridge lingers in the graph (once discovery has heard it go).
    wait_until(lambda: missing not in robot.known_actions(), what="the bridge's action client to leave the graph")
    assert robot.server.bridge.sessions and not any(s.actions.goals() for s in robot.server.bridge.sessions)


def test_rosapi_lists_the_action_servers(robot: Robot, client: roslibpy.Ros) -> None:
    servers = roslibpy.Service(client, "/rosapi/action_servers", "rosapi/GetActionServers")
    assert ACTION in servers.call(roslibpy.ServiceRequest({}), timeout=15)["action_servers"]


# ---------------------------------------------------------------------- the protocol, frame by frame


def test_feedback_comes_only_when_asked_for(robot: Robot, raw: ClientConnection) -> None:
    goal = {"op": "send_action_goal", "id": "quiet", "action": ACTION, "action_type": FIBONACCI, "args": {"order": 3}}
    raw.send(json.dumps(goal))
    frames = []
    while True:
        frame = json.loads(raw.recv(timeout=15))
        frames.append(frame["op"])
        if frame["op"] == "action_result":
            break
    assert frames == ["action_result"]
    assert frame == {
        "op": "action_result",
        "id": "quiet",
        "action": ACTION,
        "values": {"sequence": [0, 1, 1, 2, 3]},
        "status": 4,
        "result": True,
    }


def test_an_action_name_without_its_slash_and_an_id_less_goal_are_served(robot: Robot, raw: ClientConnection) -> None:
    goal = {"op": "send_action_goal", "action": ACTION.lstrip("/"), "action_type": FIBONACCI, "args": {"order": 1}}
    raw.send(json.dumps(goal))
    result = ask(raw, {"op": "set_level", "level": "error"}, op="action_result")
    assert "id" not in result and result["status"] == 4 and result["values"] == {"sequence": [0, 1, 1]}


def test_long_answers_come_in_fragments_when_asked(robot: Robot, raw: ClientConnection) -> None:
    goal = {
        "op": "send_action_goal",
        "id": "frag",
        "action": ACTION,
        "action_type": FIBONACCI,
        "args": {"order": 8},
        "fragment_size": 16,
    }
    raw.send(json.dumps(goal))
    parts: dict[int, str] = {}
    while True:
        frame = json.loads(raw.recv(timeout=15))
        assert frame["op"] == "fragment"
        parts[frame["num"]] = frame["data"]
        if len(parts) == frame["total"]:
            break
    whole = json.loads("".join(parts[i] for i in range(len(parts))))
    assert whole["op"] == "action_result" and whole["id"] == "frag" and whole["status"] == 4


def test_a_client_that_leaves_has_its_goal_cancelled(robot: Robot) -> None:
    with connect(f"ws://127.0.0.1:{robot.port}") as websocket:
        goal = {"op": "send_action_goal", "id": "bye", "action": ACTION, "action_type": FIBONACCI}
        goal.update(args={"order": 18}, feedback=True)
        ask(websocket, goal, op="action_feedback")
    wait_until(lambda: "canceled 18" in robot.nodes.lines("fibonacci"), what="the server to cancel the goal")


@pytest.mark.parametrize(
    ("frame", "says"),
    [
        ({"op": "send_action_goal", "id": "b1", "action_type": FIBONACCI}, "'action' is missing"),
        ({"op": "send_action_goal", "id": "b2", "action": "/a b", "action_type": FIBONACCI}, "is not a ROS name"),
        ({"op": "send_action_goal", "id": "b3", "action": ACTION, "args": 5}, "'args' must be an object"),
        ({"op": "send_action_goal", "id": "b4", "action": ACTION, "feedback": "yes"}, "'feedback' must be true"),
        ({"op": "send_action_goal", "id": "b5", "action": ACTION, "compression": "png"}, "compression 'png'"),
        ({"op": "send_action_goal", "id": "b6", "action": ACTION, "fragment_size": -1}, "'fragment_size' must be"),
        ({"op": "send_action_goal", "id": "b7", "action": ACTION, "action_type": "nope_msgs/action/X"}, "nope_msgs"),
        ({"op": "send_action_goal", "id": "b8", "action": ACTION, "action_type": "test_msgs/srv/Empty"}, "action type"),
        ({"op": "send_action_goal", "id": "b9", "action": ACTION, "args": {"ordr": 3}}, "no field 'ordr'"),
        ({"op": "send_action_goal", "id": "b10", "action": ACTION, "args": {"order": "five"}}, "order: expected an"),
        (
            {"op": "send_action_goal", "id": "b11", "action": ACTION, "action_type": "test_msgs/action/NestedMessage"},
            f"{ACTION} is of type test_msgs/action/Fibonacci",
        ),
        ({"op": "cancel_action_goal", "action": ACTION}, "'id' is missing"),
        ({"op": "cancel_action_goal", "id": "never-sent", "action": ACTION}, "no goal with id 'never-sent'"),
        ({"op": "cancel_action_goal", "id": "c1"}, "'action' is missing"),
        ({"op": "advertise_action", "id": "s1", "action": "/mine", "type": FIBONACCI}, "does not serve actions"),
        ({"op": "action_result", "id": "s2", "action": ACTION, "values": {}}, "does not serve actions"),
    ],
)
def test_a_bad_action_op_gets_a_status_naming_it_and_nothing_runs(
    frame: dict[str, Any], says: str, robot: Robot, raw: ClientConnection
) -> None:
    goals_before = [line for line in robot.nodes.lines("fibonacci") if line.startswith("goal ")]
    status = ask(raw, frame)
    assert status["level"] == "error" and says in status["msg"], status
    assert status["msg"].startswith(frame["op"] + ": ")
    if "id" in frame:
        assert status["id"] == frame["id"]
    goal = {"op": "send_action_goal", "id": "after", "action": ACTION, "action_type": FIBONACCI, "args": {"order": 2}}
    result = ask(raw, goal, op="action_result", match=lambda answer: answer.get("id") == "after")
    assert result["result"] is True and result["status"] == 4  # the connection keeps working
    goals = [line for line in robot.nodes.lines("fibonacci") if line.startswith("goal ")]
    assert goals == [*goals_before, "goal 2"]  # the server saw the good goal only


def test_a_goal_id_already_in_progress_is_refused(robot: Robot, raw: ClientConnection) -> None:
    goal = {"op": "send_action_goal", "id": "twice", "action": ACTION, "action_type": FIBONACCI, "args": {"order": 8}}
    raw.send(json.dumps(goal))
    status = ask(raw, goal)
    assert status["msg"] == "send_action_goal: a goal with id 'twice' is already in progress"
    result = ask(raw, {"op": "set_level", "level": "error"}, op="action_result")
    assert result["id"] == "twice" and result["values"]["sequence"][-1] == 34  # the first goal ran, once


def test_a_cancel_after_the_goal_ended_is_only_a_warning(robot: Robot, raw: ClientConnection) -> None:
    goal = {"op": "send_action_goal", "id": "ended", "action": ACTION, "action_type": FIBONACCI, "args": {"order": 1}}
    ask(raw, goal, op="action_result")
    raw.send(json.dumps({"op": "set_level", "level": "warning"}))
    status = ask(raw, {"op": "cancel_action_goal", "id": "ended", "action": ACTION})
    assert (status["level"], status["msg"]) == ("warning", "cancel_action_goal: goal 'ended' has already ended")


# ---------------------------------------------------------------------- ROS 1


@pytest.fixture(scope="module")
def ros1_door(tmp_path_factory: pytest.TempPathFactory) -> Iterator[int]:
    if not ros1_available():
        pytest.skip("Debian's ROS 1 (rospy, rosmaster) is not installed")
    from bridgeos_agent.bridges.ros1graph import Ros1Graph

    loop = LoopThread()
    with private_rosmaster(tmp_path_factory.mktemp("actions-ros1")) as master:

        async def start() -> RosbridgeServer:
            graph = Ros1Graph(master)
            await graph.start()
            server = RosbridgeServer(graph)
            await server.start("127.0.0.1", 0)
            return server

        server = loop.run(start())
        try:
            yield server.port
        finally:
            loop.run(server.close())
            loop.stop()


def test_on_ros1_a_goal_is_refused_with_the_reason(ros1_door: int) -> None:
    ros = roslibpy.Ros("127.0.0.1", ros1_door)
    ros.run(timeout=10)
    try:
        action = roslibpy.ActionClient(ros, "/fibonacci", "actionlib_tutorials/Fibonacci")
        goal_id, outcome = send(action, 3)
        action.wait_goal(goal_id, timeout=30)
    finally:
        ros.close()
    assert outcome.error is not None and outcome.error["status"] == GoalStatus.UNKNOWN
    assert "ROS 1, which has no ROS 2 actions" in outcome.error["values"]
    with connect(f"ws://127.0.0.1:{ros1_door}") as websocket:
        goal = {"op": "send_action_goal", "id": "r1", "action": "/fibonacci", "action_type": FIBONACCI}
        result = ask(websocket, goal, op="action_result")
        assert result["result"] is False and "has no ROS 2 actions" in result["values"] and result["id"] == "r1"
        status = ask(websocket, {"op": "cancel_action_goal", "id": "r2", "action": "/fibonacci"})
        assert status["msg"] == "cancel_action_goal: no goal with id 'r2' is in progress"
