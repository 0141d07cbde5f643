"""One set of behavioural tests for the Skill Router, run against ROS 1 (rospy, TCPROS) and ROS 2 (rclpy).

The same Skill, the same real talker and listener processes (tests/agent/rosnodes.py on a
private rosmaster, tests/agent/ros2nodes.py on a loopback-only ROS 2 graph) and the same
assertions: relay to the canonical name and the components' instances, outside publishers,
a talker switched under a 1 kHz stream, a listener switched, stored messages replayed to a
new instance, statistics, runtime changes.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from bridgeos_agent.delivery import delivery_totals
from bridgeos_agent.ros2graph import rclpy_missing
from bridgeos_agent.router import RouterSettings, SkillRouter
from bridgeos_agent.skillconfig import parse_skill_config
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.agent.roshelpers import Nodes, private_rosmaster

pytestmark = [pytest.mark.timeout(120)]

SKILL = "behave"


@dataclass
class World:
    """One ROS: its nodes, how its types are spelled, and what a talker needs to start cleanly."""

    ros: int
    nodes: Any
    make: Callable[..., Any]
    string: str
    # ROS 2's router opens a topic once its publisher shows up, so a talker gives the canonical
    # listeners a moment to match before its first message (ROS 1's router advertises at once).
    settle: tuple[str, ...]

    def config(self, topics: list[dict]) -> dict:
        spec = {"command": ["true"]}
        ros: Any = True if self.ros == 1 else 2
        components = {
            name: {"name": name.title(), "location": "either", "ros": ros, "robot": spec, "cloud": spec}
            for name in ("talker", "listener")
        }
        return {"skill": "Behave", "skill_id": SKILL, "components": components, "router": {"topics": topics}}

    def chatter(self, name: str = "chatter", publisher: str = "talker", subscriber: str = "listener") -> dict:
        return {"name": name, "type": self.string, "publisher": publisher, "subscribers": [subscriber]}


def ns(component: str, location: str) -> str:
    return f"/bridgeos/{SKILL}/{component}/{location}"


@pytest.fixture(params=[1, 2], ids=["ros1", "ros2"])
async def world(request, tmp_path_factory, tmp_path: Path) -> AsyncIterator[World]:
    routers: list[SkillRouter] = []
    if request.param == 1:
        stack = private_rosmaster(tmp_path_factory.mktemp("rosmaster"))
        master = stack.__enter__()
        nodes: Any = Nodes(master, tmp_path)
    else:
        if rclpy_missing():
            pytest.skip(rclpy_missing())
        stack, master = None, None
        nodes = Ros2Nodes(loopback_graph(), tmp_path)

    async def make(config: dict, **active: str) -> SkillRouter:
        settings = RouterSettings(http_host="127.0.0.1", statistics_period=0.5)
        router = SkillRouter(parse_skill_config(config), ros_master=master, settings=settings, state_dir=tmp_path)
        if request.param == 2:
            await router.set_ros2_graphs(loopback_graph())
        for component, location in active.items():
            router.set_active(component, location)
        routers.append(router)
        await router.start()
        return router

    string = "std_msgs/String" if request.param == 1 else "std_msgs/msg/String"
    settle = () if request.param == 1 else ("--settle", "2")
    try:
        yield World(request.param, nodes, make, string, settle)
    finally:
        for router in routers:
            await router.close()
        nodes.kill_all()
        if stack is not None:
            stack.__exit__(None, None, None)


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


async def test_the_active_talker_reaches_canonical_and_component_listeners_and_outside_publishers_reach_them(world):
    router = await world.make(world.config([world.chatter()]), talker="robot", listener="robot")
    nodes = world.nodes
    nodes.run("component", "listener", namespace=ns("listener", "robot"))
    nodes.run("canonical", "listener", "--topic", "/chatter")
    nodes.run("robot", "talker", "--tag", "robot", "--rate", "50", "--linger", "30", namespace=ns("talker", "robot"))
    # The idle cloud copy publishes too, but its traffic goes nowhere.
    nodes.run("cloud", "talker", "--tag", "cloud", "--rate", "50", "--linger", "30", namespace=ns("talker", "cloud"))
    assert await router.wait_ready("talker", "robot", 30)
    assert await router.wait_ready("listener", "robot", 30)
    for key in ("component", "canonical"):
        await eventually(lambda key=key: len(nodes.messages(key)) >= 20, what=f"{key} hears the talker")
        assert {tag for tag, _ in nodes.messages(key)} == {"robot"}
    nodes.run("outside", "talker", "--topic", "/chatter", "--tag", "outside", "--rate", "20", "--linger", "30")
    await eventually(
        lambda: any(tag == "outside" for tag, _ in nodes.messages("component")), what="the outside publisher"
    )
    assert {tag for tag, _ in nodes.messages("canonical")} <= {"robot", "outside"}
    stats = router.statistics()["/chatter"]
    assert stats["subscribers"]["listener"]["messages"] >= 20 and stats["dropped"] == 0


async def test_switching_the_talker_under_a_1khz_stream_loses_and_duplicates_nothing(world, tmp_path):
    router = await world.make(world.config([world.chatter()]), talker="robot", listener="robot")
    nodes = world.nodes
    nodes.run("canonical", "listener", "--topic", "/chatter")
    nodes.run("component", "listener", namespace=ns("listener", "robot"))
    assert await router.wait_ready("listener", "robot", 30)
    if world.ros == 1:
        await eventually(lambda: router.node.publications["/chatter"].connections, what="the canonical listener")
    gate = tmp_path / "go"
    args = ("--rate", "1000", "--wait", "--linger", "30", *world.settle)
    if world.ros == 2:
        args += ("--gate", str(gate))
    nodes.run("robot", "talker", "--tag", "robot", *args, namespace=ns("talker", "robot"))
    if world.ros == 2:
        # ROS 2 opens a topic's endpoints once its publisher is seen: the talker waits until both
        # listeners matched them, however slow discovery is on a loaded machine.
        def matched() -> bool:
            topic = router._topics.get("/chatter")
            pub = getattr(topic, "canonical_pub", None)
            return pub is not None and pub.get_subscription_count() > 0

        await eventually(matched, what="the canonical listener matched")
        assert await router.wait_ready("listener", "robot", 30)
    gate.touch()
    await eventually(lambda: len(nodes.messages("canonical")) >= 300, what="the robot stream")
    nodes.run("cloud", "talker", "--tag", "cloud", "--rate", "1000", "--linger", "30", namespace=ns("talker", "cloud"))
    assert await router.wait_ready("talker", "cloud", 30)
    await router.switch("talker", "cloud")
    assert router.active("talker") == "cloud"
    for key in ("canonical", "component"):
        await eventually(
            lambda key=key: [tag for tag, _ in nodes.messages(key)].count("cloud") >= 500,
            timeout=60,
            what=f"the cloud stream at the {key} listener",
        )
    for key in ("canonical", "component"):
        heard = nodes.messages(key)
        tags = [tag for tag, _ in heard]
        cut = tags.index("cloud")
        assert set(tags[:cut]) == {"robot"} and set(tags[cut:]) == {"cloud"}, f"{key}: the streams interleave"
        robot = [seq for _, seq in heard[:cut]]
        assert robot[0] == 1 and contiguous(robot), f"{key}: the robot stream lost or repeated messages"
        assert contiguous([seq for _, seq in heard[cut:]]), f"{key}: the cloud stream lost or repeated messages"
    assert router.statistics()["/chatter"]["dropped"] == 0


async def test_switching_the_listener_delivers_every_message_exactly_once(world):
    router = await world.make(world.config([world.chatter()]), talker="robot", listener="robot")
    nodes = world.nodes
    nodes.run("listener-robot", "listener", namespace=ns("listener", "robot"))
    nodes.run("listener-cloud", "listener", namespace=ns("listener", "cloud"))
    if world.ros == 1:
        assert await router.wait_ready("listener", "robot", 30)
        assert await router.wait_ready("listener", "cloud", 30)
    args = ("--tag", "t", "--rate", "1000", "--count", "3000", "--wait", "--linger", "30", *world.settle)
    nodes.run("talker", "talker", *args, namespace=ns("talker", "robot"))
    assert await router.wait_ready("talker", "robot", 30)
    assert await router.wait_ready("listener", "robot", 30)
    assert await router.wait_ready("listener", "cloud", 30)
    await eventually(lambda: len(nodes.messages("listener-robot")) >= 500, what="the robot listener hears")
    await router.switch("listener", "cloud")
    await eventually(
        lambda: any(line.startswith("sent") for line in nodes.lines("talker")), timeout=60, what="the talker ends"
    )
    await eventually(
        lambda: len(nodes.messages("listener-robot")) + len(nodes.messages("listener-cloud")) >= 3000,
        timeout=60,
        what="every message delivered",
    )
    robot = [seq for _, seq in nodes.messages("listener-robot")]
    cloud = [seq for _, seq in nodes.messages("listener-cloud")]
    assert cloud, "the cloud listener heard nothing after the switch"
    assert robot + cloud == list(range(1, 3001))


async def test_stored_messages_are_replayed_to_a_new_instance(world):
    router = await world.make(world.config([{**world.chatter(), "store": 5}]), talker="robot", listener="robot")
    nodes = world.nodes
    args = ("--tag", "t", "--rate", "100", "--count", "12", "--wait", "--linger", "30", *world.settle)
    nodes.run("talker", "talker", *args, namespace=ns("talker", "robot"))
    await eventually(lambda: router.statistics()["/chatter"]["messages"] == 12, what="12 messages routed")
    # A migrated subscriber starts in the cloud and gets the last 5 first (state sync).
    nodes.run("late", "listener", namespace=ns("listener", "cloud"))
    assert await router.wait_ready("listener", "cloud", 45)
    await eventually(lambda: len(nodes.messages("late")) >= 5, what="the replay")
    await asyncio.sleep(0.3)
    assert nodes.messages("late") == [("t", seq) for seq in range(8, 13)]


async def test_statistics_count_what_was_routed(world, tmp_path):
    router = await world.make(world.config([world.chatter()]), talker="robot", listener="robot")
    nodes = world.nodes
    nodes.run("listener", "listener", namespace=ns("listener", "robot"))
    if world.ros == 1:
        assert await router.wait_ready("listener", "robot", 30)
    gate = tmp_path / "go"
    args = ("--tag", "s", "--rate", "200", "--count", "200", "--wait", "--linger", "30", *world.settle)
    if world.ros == 2:
        args += ("--gate", str(gate))
    nodes.run("talker", "talker", *args, namespace=ns("talker", "robot"))
    if world.ros == 2:
        # The listener's delivery opens once the talker is seen: the talker starts only when the
        # listener has matched that delivery (a fixed settle lost the first messages on loaded CI).
        def matched() -> bool:
            topic = router._topics.get("/chatter")
            delivery = topic.deliveries.get("listener") if topic is not None else None
            sink = delivery.robot if delivery is not None else None
            return sink is not None and sink.get_subscription_count() > 0

        await eventually(matched, what="the listener matched the router's delivery")
    gate.touch()
    await eventually(lambda: len(nodes.messages("listener")) >= 200, what="every message")
    stats = router.statistics()["/chatter"]
    assert stats["messages"] == 200 and stats["subscribers"]["listener"]["messages"] == 200
    assert stats["dropped"] == 0 and stats["delivery_ratio"] == 1.0 and stats["bytes"] > 0
    # What the robot reports for a rollout's router gate: every message delivered, none dropped.
    assert delivery_totals(router.statistics()) == (stats["delivered"], 0) and stats["delivered"] >= 200
    traffic = router.traffic("talker")
    assert traffic.messages == 200 and traffic.dropped == 0 and traffic.bytes_robot > 0


async def test_topics_are_added_and_removed_at_runtime(world):
    router = await world.make(world.config([world.chatter()]), talker="robot", listener="robot")
    extra = world.chatter("/scan", publisher="listener", subscriber="talker")
    await router.apply(parse_skill_config(world.config([extra])))
    assert set(router.statistics()) == {"/scan"}
    nodes = world.nodes
    nodes.run("heard", "listener", "--topic", "scan", namespace=ns("talker", "robot"))
    nodes.run("scan", "talker", "--topic", "scan", "--rate", "50", "--linger", "30", namespace=ns("listener", "robot"))
    await eventually(lambda: len(nodes.messages("heard")) >= 5, what="the new topic is routed")
    # And the removed one is no longer routed: its talker reaches nobody.
    nodes.run("old", "talker", "--rate", "50", "--linger", "30", namespace=ns("talker", "robot"))
    nodes.run("old-listener", "listener", namespace=ns("listener", "robot"))
    await asyncio.sleep(2)
    assert nodes.messages("old-listener") == [] and set(router.statistics()) == {"/scan"}
