"""The Skill Router's ROS 2 routes against real rclpy nodes (subprocesses) on a loopback-only graph."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path

import pytest

from bridgeos_agent.ros2graph import Ros2Graph, discovery_server_command, rclpy_missing
from bridgeos_agent.router import RouterSettings, SkillRouter
from bridgeos_agent.skillconfig import parse_skill_config
from tests.agent.ros2helpers import Ros2Nodes, test_graph
from tests.conftest import free_port

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
        for name in ("talker", "listener", "server")
    }
    return {"skill": "Relay2", "skill_id": SKILL, "components": components, "router": router}


async def eventually(check: Callable[[], object], timeout: float = 30.0, what: str = "condition") -> object:
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.05)


def contiguous(seqs: list[int]) -> bool:
    return seqs == list(range(seqs[0], seqs[0] + len(seqs))) if seqs else True


@pytest.fixture
def nodes(tmp_path: Path) -> Iterator[Ros2Nodes]:
    runner = Ros2Nodes(test_graph(), tmp_path)
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
        await router.set_ros2_graphs(test_graph(), cloud)
        for component, location in active.items():
            router.set_active(component, location)
        routers.append(router)
        await router.start()
        return router

    yield make
    for router in routers:
        await router.close()


async def test_the_active_talker_reaches_the_component_and_canonical_listeners_and_outside_publishers_too(
    nodes, make_router
):
    router = await make_router(skill({"topics": [CHATTER]}), talker="robot", listener="robot")
    assert router.ros2_on and not router.ros_on
    nodes.run("component", "listener", namespace=ns("listener", "robot"))
    nodes.run("canonical", "listener", "--topic", "/chatter")
    nodes.run("robot", "talker", "--tag", "robot", "--rate", "50", namespace=ns("talker", "robot"))
    nodes.run("cloud", "talker", "--tag", "cloud", "--rate", "50", namespace=ns("talker", "cloud"))
    assert await router.wait_ready("talker", "robot", 30)
    assert await router.wait_ready("listener", "robot", 30)
    for key in ("component", "canonical"):
        await eventually(lambda key=key: len(nodes.messages(key)) >= 20, what=f"{key} hears the talker")
        assert {tag for tag, _ in nodes.messages(key)} == {"robot"}
    nodes.run("outside", "talker", "--tag", "outside", "--rate", "20", "--topic", "/chatter")
    await eventually(lambda: ("outside", 3) in nodes.messages("component"), what="the outside message at the component")
    # The router never hears its own canonical publication back as an outside one.
    assert {tag for tag, _ in nodes.messages("canonical")} <= {"robot", "outside"}
    stats = router.statistics()["/chatter"]
    assert stats["subscribers"]["listener"]["messages"] >= 20 and stats["dropped"] == 0


async def test_switching_the_talker_under_a_1khz_stream_loses_and_duplicates_nothing(nodes, make_router):
    router = await make_router(skill({"topics": [CHATTER]}), talker="robot", listener="robot")
    nodes.run("canonical", "listener", "--topic", "/chatter")
    nodes.run("component", "listener", namespace=ns("listener", "robot"))
    nodes.run("robot", "talker", "--tag", "robot", "--rate", "1000", "--wait", namespace=ns("talker", "robot"))
    await eventually(lambda: len(nodes.messages("canonical")) >= 300, what="the robot stream")
    nodes.run("cloud", "talker", "--tag", "cloud", "--rate", "1000", namespace=ns("talker", "cloud"))
    assert await router.wait_ready("talker", "cloud", 30)
    await router.switch("talker", "cloud")
    switched_at = len(nodes.messages("canonical"))
    await eventually(lambda: len(nodes.messages("canonical")) >= switched_at + 500, what="the cloud stream")
    for key in ("canonical", "component"):
        heard = nodes.messages(key)
        tags = [tag for tag, _ in heard]
        cut = tags.index("cloud")
        assert set(tags[:cut]) == {"robot"} and set(tags[cut:]) == {"cloud"}, f"{key}: the streams interleave"
        assert heard[0] == ("robot", 1) and contiguous([s for _, s in heard[:cut]]), f"{key}: robot stream"
        assert contiguous([s for _, s in heard[cut:]]), f"{key}: the cloud stream lost or repeated messages"


async def test_switching_the_listener_delivers_every_message_exactly_once(nodes, make_router):
    router = await make_router(skill({"topics": [CHATTER]}), talker="robot", listener="robot")
    nodes.run("listener-robot", "listener", namespace=ns("listener", "robot"))
    nodes.run("listener-cloud", "listener", namespace=ns("listener", "cloud"))
    args = ("--tag", "t", "--rate", "1000", "--count", "3000", "--wait", "--settle", "1")
    nodes.run("talker", "talker", *args, namespace=ns("talker", "robot"))
    await eventually(lambda: router.statistics()["/chatter"]["messages"], what="the talker is routed")
    assert await router.wait_ready("listener", "robot", 30)
    assert await router.wait_ready("listener", "cloud", 30)
    await eventually(lambda: len(nodes.messages("listener-robot")) >= 500, what="the robot listener hears")
    await router.switch("listener", "cloud")
    await eventually(
        lambda: len(nodes.messages("listener-robot")) + len(nodes.messages("listener-cloud")) >= 3000,
        what="every message delivered",
    )
    robot = [seq for _, seq in nodes.messages("listener-robot")]
    cloud = [seq for _, seq in nodes.messages("listener-cloud")]
    assert cloud and robot + cloud == list(range(1, 3001))


async def test_a_transient_local_map_reaches_a_late_joiner_and_best_effort_stays_best_effort(nodes, make_router):
    routes = [
        {"name": "/map", "type": "nav_msgs/msg/OccupancyGrid", "publisher": "server", "subscribers": []},
        {"name": "/map_tag", "type": "std_msgs/msg/String", "publisher": "server", "subscribers": []},
        {**CHATTER, "name": "/scan_tag"},
    ]
    router = await make_router(skill({"topics": routes}), talker="robot", listener="robot", server="robot")
    # One latched message, published long before anyone listens.
    nodes.run("map", "talker", "--topic", "map_tag", "--latched", "--depth", "1", "--count", "1", "--rate", "0",
              "--tag", "map", "--linger", "60", namespace=ns("server", "robot"))
    nodes.run("scan", "talker", "--topic", "scan_tag", "--best-effort", "--rate", "50",
              namespace=ns("talker", "robot"))
    await eventually(lambda: router.statistics()["/map_tag"]["messages"] == 1, what="the map reaches the router")
    await asyncio.sleep(1.0)
    nodes.run("late", "listener", "--topic", "/map_tag", "--latched", "--depth", "1")
    await eventually(lambda: nodes.messages("late") == [("map", 1)], what="the late joiner gets the map")
    # A best-effort listener hears the best-effort stream (the router offers what the publisher offers).
    nodes.run("fast", "listener", "--topic", "/scan_tag", "--best-effort")
    await eventually(lambda: len(nodes.messages("fast")) >= 10, what="the best-effort listener hears")


async def test_a_service_call_reaches_the_active_server_instance(nodes, make_router):
    route = {"name": "/trigger", "type": "std_srvs/srv/Trigger", "server": "server"}
    router = await make_router(skill({"services": [route]}), server="robot")
    nodes.run("robot", "server", "--topic", "trigger", "--tag", "robot", namespace=ns("server", "robot"))
    nodes.run("cloud", "server", "--topic", "trigger", "--tag", "cloud", namespace=ns("server", "cloud"))
    assert await router.wait_ready("server", "robot", 30)
    assert await router.wait_ready("server", "cloud", 30)
    answers = []
    import rclpy
    from rclpy.context import Context
    from std_srvs.srv import Trigger

    context = Context()
    rclpy.init(context=context, domain_id=test_graph().domain_id)
    node = rclpy.create_node("caller", context=context)
    try:
        client = node.create_client(Trigger, "/trigger")
        assert await asyncio.to_thread(client.wait_for_service, 20)
        for where in ("robot", "cloud"):
            await router.switch("server", where)
            future = client.call_async(Trigger.Request())
            await asyncio.to_thread(rclpy.spin_until_future_complete, node, future, None, 20)
            answers.append(future.result().message)
    finally:
        node.destroy_node()
        context.try_shutdown()
    assert answers == ["robot", "cloud"]
    assert router.statistics()["/trigger"]["calls"] == 2


async def test_an_action_is_relayed_with_its_feedback_and_result(nodes, make_router):
    action = {"name": "/fibonacci", "type": "test_msgs/action/Fibonacci", "server": "server"}
    router = await make_router(skill({"actions": [action]}), server="robot")
    nodes.run("robot", "action", "--topic", "fibonacci", namespace=ns("server", "robot"))
    assert await router.wait_ready("server", "robot", 30)
    import rclpy
    from rclpy.action import ActionClient
    from rclpy.context import Context
    from test_msgs.action import Fibonacci

    context = Context()
    rclpy.init(context=context, domain_id=test_graph().domain_id)
    node = rclpy.create_node("action_caller", context=context)
    feedback = []
    try:
        client = ActionClient(node, Fibonacci, "/fibonacci")
        assert await asyncio.to_thread(client.wait_for_server, 20)
        sent = client.send_goal_async(Fibonacci.Goal(order=5), feedback_callback=lambda f: feedback.append(f))
        await asyncio.to_thread(rclpy.spin_until_future_complete, node, sent, None, 20)
        goal = sent.result()
        assert goal.accepted
        result = goal.get_result_async()
        await asyncio.to_thread(rclpy.spin_until_future_complete, node, result, None, 20)
        assert list(result.result().result.sequence) == [0, 1, 1, 2, 3, 5, 8]
    finally:
        node.destroy_node()
        context.try_shutdown()
    assert feedback, "no feedback came through the router"


async def test_topics_are_added_and_removed_at_runtime(nodes, make_router):
    router = await make_router(skill({"topics": [CHATTER]}), talker="robot", listener="robot")
    extra = {"name": "/scan", "type": "std_msgs/msg/String", "publisher": "listener", "subscribers": ["talker"]}
    await router.apply(parse_skill_config(skill({"topics": [extra]})))
    assert set(router.statistics()) == {"/scan"}
    nodes.run("scan", "talker", "--topic", "scan", "--rate", "50", namespace=ns("listener", "robot"))
    nodes.run("heard", "listener", "--topic", "scan", namespace=ns("talker", "robot"))
    await eventually(lambda: len(nodes.messages("heard")) >= 5, what="the new topic is routed")


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
    await router.set_ros2_graphs(test_graph())
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
        nodes.run("reliable", "listener", namespace=ns("listener", "robot"), *("--topic", "qos"))
        await eventually(lambda: "/qos" in router.route_errors, what="the QoS mismatch")
        assert "QoS" in router.route_errors["/qos"]
        assert {name for name, _ in errors} == {"/unknown", "/missing", "/wrong", "/qos"}
    finally:
        await router.close()


async def test_cloud_instances_are_reached_through_the_robots_discovery_server(nodes, make_router, tmp_path):
    import subprocess

    port = free_port()
    argv, env = discovery_server_command("127.0.0.1", port)
    import os

    server = subprocess.Popen(argv, env={**os.environ, **env}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        cloud = Ros2Graph(domain_id=test_graph().domain_id, discovery_server=f"127.0.0.1:{port}")
        router = await make_router(skill({"topics": [CHATTER]}), cloud=cloud, talker="cloud", listener="robot")
        assert set(router._r2_sides) == {"robot", "cloud"}
        nodes.run("talker", "talker", "--tag", "c", "--rate", "50", namespace=ns("talker", "cloud"), graph=cloud)
        nodes.run("listener", "listener", namespace=ns("listener", "robot"))
        assert await router.wait_ready("talker", "cloud", 30)
        await eventually(lambda: len(nodes.messages("listener")) >= 10, what="the cloud talker reaches the robot")
    finally:
        server.kill()
        server.wait(10)
