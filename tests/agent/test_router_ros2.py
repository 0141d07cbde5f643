"""The Skill Router's ROS 2 routes against real rclpy nodes (subprocesses) on a loopback-only graph."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path

import pytest

from bridgeos_agent.ros2graph import Ros2Graph, discovery_server_command, rclpy_missing
from bridgeos_agent.router import RouterSettings, SkillRouter
from bridgeos_agent.skillconfig import parse_skill_config
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.conftest import eventually, free_port

pytestmark = [
    pytest.mark.timeout(120),
    pytest.mark.skipif(rclpy_missing() is not None, reason="rclpy is not installed"),
]

SKILL = "relay2"
CHATTER = {"name": "chatter", "type": "std_msgs/msg/String", "publisher": "talker", "subscribers": ["listener"]}


def ns(component: str, location: str) -> str:
    return f"/bridgeos/{SKILL}/{component}/{location}"


def skill(router: dict, ros: int = 2) -> dict:
    spec = {"command": ["true"]}
    components = {
        name: {"name": name.title(), "location": "either", "ros": ros, "robot": spec, "cloud": spec}
        for name in ("talker", "listener", "server", "viewer")
    }
    return {"skill": "Relay2", "skill_id": SKILL, "components": components, "router": router}


def contiguous(seqs: list[int]) -> bool:
    return seqs == list(range(seqs[0], seqs[0] + len(seqs))) if seqs else True


@pytest.fixture
def nodes(tmp_path: Path) -> Iterator[Ros2Nodes]:
    runner = Ros2Nodes(loopback_graph(), tmp_path)
    try:
        yield runner
    finally:
        runner.kill_all()


@pytest.fixture
async def make_router(tmp_path: Path) -> AsyncIterator[Callable[..., object]]:
    routers: list[SkillRouter] = []

    async def make(config: dict, cloud: Ros2Graph | None = None, **active: str) -> SkillRouter:
        settings = RouterSettings(http_host="127.0.0.1", statistics_period=0.5)
        router = SkillRouter(parse_skill_config(config), ros_master=None, settings=settings, state_dir=tmp_path)
        await router.set_ros2_graphs(loopback_graph(), cloud)
        for component, location in active.items():
            router.set_active(component, location)
        routers.append(router)
        await router.start()
        return router

    yield make
    for router in routers:
        await router.close()


async def test_a_transient_local_map_reaches_a_late_joiner_and_best_effort_stays_best_effort(nodes, make_router):
    routes = [
        {"name": "/map", "type": "nav_msgs/msg/OccupancyGrid", "publisher": "server", "subscribers": []},
        {"name": "/map_tag", "type": "std_msgs/msg/String", "publisher": "server", "subscribers": ["viewer"]},
        {**CHATTER, "name": "/scan_tag"},
    ]
    router = await make_router(skill({"topics": routes}), talker="robot", listener="robot", server="robot")
    # One latched message, published long before anyone listens.
    nodes.run(
        "map",
        "talker",
        "--topic",
        "map_tag",
        "--latched",
        "--depth",
        "1",
        "--count",
        "1",
        "--rate",
        "0",
        "--tag",
        "map",
        "--linger",
        "60",
        namespace=ns("server", "robot"),
    )
    nodes.run("scan", "talker", "--topic", "scan_tag", "--best-effort", "--rate", "50", namespace=ns("talker", "robot"))
    await eventually(lambda: router.statistics()["/map_tag"]["messages"] == 1, what="the map reaches the router")
    await asyncio.sleep(1.0)
    nodes.run("late", "listener", "--topic", "/map_tag", "--latched", "--depth", "1")
    await eventually(lambda: nodes.messages("late") == [("map", 1)], what="the late joiner gets the map")
    # A viewer component placed in the cloud long after the map was sent gets it too.
    nodes.run("moved", "listener", "--topic", "map_tag", "--latched", "--depth", "1", namespace=ns("viewer", "cloud"))
    assert await router.wait_ready("viewer", "cloud", 30)
    await eventually(lambda: nodes.messages("moved") == [("map", 1)], what="the moved listener gets the map")
    # A best-effort listener hears the best-effort stream (the router offers what the publisher offers).
    nodes.run("fast", "listener", "--topic", "/scan_tag", "--best-effort")
    await eventually(lambda: len(nodes.messages("fast")) >= 10, what="the best-effort listener hears")


async def test_a_service_call_reaches_the_active_server_instance_and_a_switch_waits_for_calls_on_their_way(
    nodes, make_router
):
    route = {"name": "/trigger", "type": "std_srvs/srv/Trigger", "server": "server"}
    router = await make_router(skill({"services": [route]}), server="robot")
    nodes.run(
        "robot", "server", "--topic", "trigger", "--tag", "robot", "--delay", "1.5", namespace=ns("server", "robot")
    )
    nodes.run("cloud", "server", "--topic", "trigger", "--tag", "cloud", namespace=ns("server", "cloud"))
    assert await router.wait_ready("server", "robot", 30)
    assert await router.wait_ready("server", "cloud", 30)
    answers = []
    import rclpy
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from std_srvs.srv import Trigger

    context = Context()
    rclpy.init(context=context, domain_id=loopback_graph().domain_id)
    node = rclpy.create_node("caller", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    try:
        client = node.create_client(Trigger, "/trigger")
        assert await asyncio.to_thread(client.wait_for_service, 20.0)
        # A slow call to the robot instance is on its way when the server moves to the cloud:
        # the switch returns only once the robot instance has answered it.
        sent = time.monotonic()
        future = client.call_async(Trigger.Request())
        spun = asyncio.create_task(asyncio.to_thread(executor.spin_until_future_complete, future, 20))
        await eventually(lambda: router._inflight.get(("server", "robot")), what="the call reaches the router")
        await router.switch("server", "cloud")
        assert time.monotonic() - sent > 1.3, "the switch returned before the call on its way was answered"
        await spun
        answers.append(future.result().message)
        future = client.call_async(Trigger.Request())
        await asyncio.to_thread(executor.spin_until_future_complete, future, 20)
        answers.append(future.result().message)
    finally:
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()
    assert answers == ["robot", "cloud"]
    totals = router.statistics()["/trigger"]
    assert totals["calls"] == 2
    assert totals["bytes"] > 2 * len("robot")  # the requests' and answers' serialized bytes


async def test_an_action_is_relayed_with_its_feedback_and_result(nodes, make_router):
    action = {"name": "/fibonacci", "type": "test_msgs/action/Fibonacci", "server": "server"}
    router = await make_router(skill({"actions": [action]}), server="robot")
    nodes.run("robot", "action", "--topic", "fibonacci", namespace=ns("server", "robot"))
    assert await router.wait_ready("server", "robot", 30)
    import rclpy
    from rclpy.action import ActionClient
    from rclpy.context import Context
    from rclpy.executors import SingleThreadedExecutor
    from test_msgs.action import Fibonacci

    context = Context()
    rclpy.init(context=context, domain_id=loopback_graph().domain_id)
    node = rclpy.create_node("action_caller", context=context)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    feedback = []
    try:
        client = ActionClient(node, Fibonacci, "/fibonacci")
        assert await asyncio.to_thread(client.wait_for_server, 20)
        sent = client.send_goal_async(Fibonacci.Goal(order=5), feedback_callback=lambda f: feedback.append(f))
        await asyncio.to_thread(executor.spin_until_future_complete, sent, 20)
        goal = sent.result()
        assert goal.accepted
        result = goal.get_result_async()
        await asyncio.to_thread(executor.spin_until_future_complete, result, 20)
        assert list(result.result().result.sequence) == [0, 1, 1, 2, 3, 5, 8]
    finally:
        executor.shutdown()
        node.destroy_node()
        context.try_shutdown()
    assert feedback, "no feedback came through the router"


async def test_an_instance_gets_endpoints_only_once_placed_and_then_hears(nodes, make_router):
    # Fast DDS pairs each new endpoint with all of its participant's: unplaced instances stay closed.
    router = await make_router(skill({"topics": [CHATTER]}), talker="robot", listener="robot")
    graph = router._r2_sides["robot"].node
    nodes.run("robot", "listener", "--topic", "chatter", namespace=ns("listener", "robot"))
    nodes.run("cloud", "listener", "--topic", "chatter", namespace=ns("listener", "cloud"))
    nodes.run("talk", "talker", "--topic", "chatter", "--rate", "50", namespace=ns("talker", "robot"))
    await eventually(lambda: len(nodes.messages("robot")) >= 5, what="the robot listener hears")
    assert graph.count_publishers(f"{ns('listener', 'cloud')}/chatter") == 0
    assert graph.count_subscribers(f"{ns('talker', 'cloud')}/chatter") == 0
    assert nodes.messages("cloud") == []
    # The controller places the cloud instance and waits for it: its endpoint opens and matches.
    assert await router.wait_ready("listener", "cloud", 30)
    assert graph.count_publishers(f"{ns('listener', 'cloud')}/chatter") == 1
    await router.switch("listener", "cloud")
    await eventually(lambda: len(nodes.messages("cloud")) >= 5, what="the cloud listener hears after the switch")
    heard = len(nodes.messages("robot"))
    await asyncio.sleep(0.5)
    assert len(nodes.messages("robot")) == heard, "the robot instance still hears after the switch"


@pytest.mark.log_errors(r"skill relay2: ROS 2 route /(unknown|missing|wrong|qos): ")
async def test_bad_input_is_reported_with_the_topic_and_the_reason_and_starts_nothing_of_it(nodes, make_router):
    errors = []
    routes = [
        {**CHATTER, "name": "/unknown", "type": "std_msgs/msg/NoSuchType"},
        {**CHATTER, "name": "/missing", "type": "no_such_msgs/msg/Thing"},
        {**CHATTER, "name": "/wrong", "type": "std_msgs/msg/Int32"},
        {**CHATTER, "name": "/qos", "type": "std_msgs/msg/String"},
    ]
    config = skill({"topics": routes})
    settings = RouterSettings(http_host="127.0.0.1")
    router = SkillRouter(parse_skill_config(config), ros_master=None, settings=settings)
    router.on_route_error = lambda name, reason: errors.append((name, reason))
    await router.set_ros2_graphs(loopback_graph())
    router.set_active("talker", "robot")
    router.set_active("listener", "robot")
    try:
        started = time.monotonic()
        await router.start()
        assert time.monotonic() - started < 15
        assert "no msg 'NoSuchType'" in router.route_errors["/unknown"]
        assert "'no_such_msgs' is not installed" in router.route_errors["/missing"]
        assert set(router.statistics()) == {"/wrong", "/qos"}  # nothing of the bad routes started
        # A publisher of another type than the route says.
        nodes.run("wrong", "talker", "--topic", "wrong", namespace=ns("talker", "robot"))
        await eventually(lambda: "/wrong" in router.route_errors, what="the type mismatch")
        assert "std_msgs/msg/String" in router.route_errors["/wrong"]
        # A reliable listener of a best-effort publisher: reported, not hung.
        nodes.run("be", "talker", "--topic", "qos", "--best-effort", namespace=ns("talker", "robot"))
        await eventually(lambda: router.statistics()["/qos"]["messages"], what="the best-effort stream is routed")
        nodes.run("reliable", "listener", "--topic", "qos", namespace=ns("listener", "robot"))
        await eventually(lambda: "/qos" in router.route_errors, what="the QoS mismatch")
        assert "QoS" in router.route_errors["/qos"]
        assert {name for name, _ in errors} == {"/unknown", "/missing", "/wrong", "/qos"}
    finally:
        await router.close()


@pytest.fixture
def discovery_server() -> Iterator[str]:
    """Run a Fast DDS discovery server on loopback (the cloud runs one per robot)."""
    port = free_port()
    argv, env = discovery_server_command("127.0.0.1", port)
    server = subprocess.Popen(argv, env={**os.environ, **env}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        yield f"127.0.0.1:{port}"
    finally:
        server.kill()
        server.wait(10)


# Fast DDS makes every participant created after a discovery-server client a client too, so the
# suite's process must never hold one: the next test would get deaf robot graphs.
IN_A_PROCESS_OF_ITS_OWN = os.environ.get("BRIDGEOS_TEST_DDS_CHILD") == "1"


def test_the_discovery_server_path_runs_in_a_process_of_its_own() -> None:
    test = "test_cloud_instances_are_reached_through_the_robots_discovery_server"
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", f"{__file__}::{test}"],
        env={**os.environ, "BRIDGEOS_TEST_DDS_CHILD": "1"},
        capture_output=True,
        text=True,
        timeout=110,
    )
    assert done.returncode == 0 and "1 passed" in done.stdout, done.stdout[-4000:] + done.stderr[-2000:]


@pytest.mark.skipif(
    not IN_A_PROCESS_OF_ITS_OWN, reason="run by test_the_discovery_server_path_runs_in_a_process_of_its_own"
)
async def test_cloud_instances_are_reached_through_the_robots_discovery_server(nodes, make_router, discovery_server):
    # The cloud talker is a client of the discovery server only: the robot's graph cannot see it,
    # so what the listener hears came through the router's "cloud" context.
    cloud = Ros2Graph(domain_id=loopback_graph().domain_id, discovery_server=discovery_server)
    router = await make_router(skill({"topics": [CHATTER]}), cloud=cloud, talker="cloud", listener="robot")
    assert set(router._r2_sides) == {"robot", "cloud"}
    nodes.run("talker", "talker", "--tag", "c", "--rate", "50", namespace=ns("talker", "cloud"), graph=cloud)
    nodes.run("listener", "listener", namespace=ns("listener", "robot"))
    assert await router.wait_ready("talker", "cloud", 30)
    await eventually(lambda: len(nodes.messages("listener")) >= 10, what="the cloud talker reaches the robot")
    assert {tag for tag, _ in nodes.messages("listener")} == {"c"}


QOS_PROBE = """
import time, rclpy
from rclpy.duration import Duration
from rclpy.qos import DurabilityPolicy, QoSProfile, qos_check_compatible
from std_msgs.msg import String
from bridgeos_agent.router.ros2discovery import _as_asked
rclpy.init()
node = rclpy.create_node("qos_probe")
node.create_subscription(String, "plain", lambda m: None, 10)
strict = QoSProfile(depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL, deadline=Duration(seconds=1))
node.create_subscription(String, "strict", lambda m: None, strict)
time.sleep(0.5)
for topic in ("plain", "strict"):
    asked = node.get_subscriptions_info_by_topic("/" + topic)[0].qos_profile
    print(topic, qos_check_compatible(QoSProfile(depth=10), _as_asked(asked))[0].name)
rclpy.shutdown()
"""


def test_a_subscriber_that_asks_for_no_deadline_is_not_taken_for_an_incompatible_one():
    env = {**os.environ, **loopback_graph().env()}
    env["ROS_DOMAIN_ID"] = str(int(os.environ.get("ROS_DOMAIN_ID") or 44) + 1)  # a graph of its own
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    done = subprocess.run([sys.executable, "-c", QOS_PROBE], capture_output=True, text=True, env=env, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == ["plain", "OK", "strict", "ERROR"]
