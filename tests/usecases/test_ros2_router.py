"""The use cases end to end through the Skill Router: ROS 2 nodes in instance namespaces, outputs on canonical names.

The router (in this process, rclpy) relays between each component instance's namespace and the
Skill's canonical names, as the agent runs it; the nodes are the real use-case nodes. People
detection moves its sampler and detector from the robot to the cloud while a listener keeps
hearing people; a mixed Skill routes ROS 1 navigation and ROS 2 mapping side by side.
"""

from __future__ import annotations

import asyncio
import copy
import json
import math
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bridgeos_agent.ros2graph import Ros2Graph
from bridgeos_agent.rosnames import instance_namespace
from bridgeos_agent.router import RouterSettings, SkillRouter
from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_agent.usecases.occupancy import map_agreement
from bridgeos_agent.usecases.world import get_world
from tests.usecases.conftest import Nodes, RosMaster
from tests.usecases.ros2help import GRAPH_ENV

pytestmark = pytest.mark.timeout(150)

PATH_PROBE = """
import json, sys, rospy
from nav_msgs.msg import Path
rospy.init_node("probe", anonymous=True, disable_signals=True)
msg = rospy.wait_for_message("/path", Path, timeout=float(sys.argv[1]))
print(json.dumps([[p.pose.position.x, p.pose.position.y] for p in msg.poses]))
"""


def sample(name: str) -> dict[str, Any]:
    """Return a sample Skill as JSON data, without HTTP routes (their fixed ports are not the test's)."""
    from importlib import resources

    config = json.loads(resources.files("bridgeos_agent").joinpath("samples", f"{name}.json").read_text())
    config["router"]["http"] = []
    return config


def mixed_skill() -> dict[str, Any]:
    """Return one Skill of ROS 1 navigation and ROS 2 mapping (its robot renamed sim2).

    Both call a topic "map": navigation's (ROS 1) is routed; mapping's built map is read on its instance name.
    """
    navigation, mapping = sample("navigation"), sample("mapping_ros2")
    skill = copy.deepcopy(navigation)
    skill["skill"], skill["skill_id"] = "Navigation and mapping", "navmap"
    for topic in mapping["router"]["topics"]:
        if topic["name"] == "map":
            continue
        topic["publisher"] = "sim2" if topic["publisher"] == "sim" else topic["publisher"]
        topic["subscribers"] = ["sim2" if s == "sim" else s for s in topic["subscribers"]]
        skill["router"]["topics"].append(topic)
    mapping["components"]["sim"]["name"] = "Simulated robot (ROS 2)"
    for cid, component in mapping["components"].items():
        skill["components"]["sim2" if cid == "sim" else cid] = component
    return skill


def graph() -> Ros2Graph:
    return Ros2Graph(domain_id=int(GRAPH_ENV["ROS_DOMAIN_ID"]), discovery_range="LOCALHOST")


@pytest.fixture
async def make_router(tmp_path: Path, ros2) -> AsyncIterator[Callable[..., Any]]:
    """Make Skill Routers (ROS 2 graph: the test's; ROS 1: the master given) and close them afterwards."""
    routers: list[SkillRouter] = []

    async def make(config: dict[str, Any], master: str | None = None, **active: str) -> SkillRouter:
        settings = RouterSettings(http_host="127.0.0.1", statistics_period=0.5)
        router = SkillRouter(parse_skill_config(config), ros_master=master, settings=settings, state_dir=tmp_path)
        await router.set_ros2_graphs(graph(), None)
        for component, location in active.items():
            router.set_active(component, location)
        routers.append(router)
        await router.start()
        return router

    yield make
    for router in routers:
        await router.close()


async def ready(router: SkillRouter, skill: str, nodes: Any, *pairs: tuple[str, str]) -> None:
    for component, location in pairs:
        if not await router.wait_ready(component, location, 40):
            pytest.fail(f"{component}@{location} never became ready\n{nodes.all_logs()}")


async def test_people_detection_through_the_router_keeps_finding_people_while_it_moves_to_the_cloud(
    ros2, make_router
) -> None:
    from geometry_msgs.msg import PoseArray

    nodes, listener = ros2
    config = sample("people_detection_ros2")
    skill = config["skill_id"]
    router = await make_router(config, pointcloud="robot", sampler="robot", detector="robot")
    assert router.ros2_on and not router.ros_on

    def ns(component: str, where: str = "robot") -> str:
        return instance_namespace(skill, component, where)

    people = [(2.5, 0.8), (4.0, -1.0), (5.5, 0.6)]
    spots = ";".join(f"{x},{y}" for x, y in people)
    nodes.start("pointcloud", "pointcloud", "--rate", "2", "--people", spots, namespace=ns("pointcloud"))
    for where in ("robot", "cloud"):  # the cloud copies start before the move, as the agent starts them
        nodes.start(f"sampler-{where}", "sampler", "--voxel", "0.05", namespace=ns("sampler", where))
        nodes.start(f"detector-{where}", "detector", namespace=ns("detector", where))
    await ready(router, skill, nodes, ("pointcloud", "robot"), ("sampler", "robot"), ("detector", "robot"))
    probe = listener("/")

    def three(message: Any) -> bool:
        return len(message.poses) == len(people)

    found = await asyncio.to_thread(probe.wait_for, PoseArray, "/people", 10, three, 40)
    spotted = [(p.position.x, p.position.y) for p in found.poses]
    for x, y in people:
        assert min(math.dist((x, y), d) for d in spotted) < 0.35, f"no detection near {(x, y)}: {spotted}"

    assert "metric pointcloud_processing_ms" not in nodes.log("detector-cloud"), "an inactive instance got clouds"
    await ready(router, skill, nodes, ("sampler", "cloud"), ("detector", "cloud"))
    await router.switch("detector", "cloud")
    await router.switch("sampler", "cloud")
    again = await asyncio.to_thread(probe.wait_for, PoseArray, "/people", 10, three, 40)
    assert len(again.poses) == len(people)
    await asyncio.to_thread(nodes.wait_for, "detector-cloud", r"metric pointcloud_processing_ms=[\d.]+", 30)
    stats = router.statistics()
    assert stats["/people"]["messages"] > 0 and stats["/pointcloud"]["messages"] > 0, stats


async def test_navigation_through_the_router_plans_in_the_cloud_and_the_robot_reaches_its_goal(
    ros2, make_router
) -> None:
    from nav_msgs.msg import Path as PathMsg

    from bridgeos_agent.usecases.ros2.node import latched

    nodes, listener = ros2
    config = sample("navigation_ros2")
    skill = config["skill_id"]
    world = get_world("room")
    router = await make_router(config, sim="robot", planner="cloud", **{"map-server": "robot", "mover": "robot"})
    assert router.ros2_on
    nodes.start("sim", "sim", "--world", "room", "--speed", "1.0", namespace=instance_namespace(skill, "sim", "robot"))
    nodes.start(
        "map-server",
        "map-server",
        "--world",
        "room",
        "--period",
        "30",  # once, then rarely: the planner gets the map by transient-local durability through the router
        namespace=instance_namespace(skill, "map-server", "robot"),
    )
    nodes.start("planner", "planner", namespace=instance_namespace(skill, "planner", "cloud"))
    nodes.start(
        "mover",
        "mover",
        "--world",
        "room",
        "--loops",
        "1",
        "--tolerance",
        "0.2",
        namespace=instance_namespace(skill, "mover", "robot"),
    )
    probe = listener("/")
    plan = await asyncio.to_thread(probe.wait_for, PathMsg, "/path", latched(), lambda m: len(m.poses) > 0, 50)
    path = [(p.pose.position.x, p.pose.position.y) for p in plan.poses]
    assert len(path) >= 3 and math.dist(path[-1], world.goals[0]) < 1e-6, path
    await asyncio.to_thread(nodes.wait_for, "mover", r"metric tour_duration_s=[\d.]+", 50)


async def test_a_mixed_skill_routes_ros1_navigation_and_ros2_mapping_side_by_side(
    ros2, make_router, ros_master: RosMaster, nodes: Nodes
) -> None:
    from nav_msgs.msg import OccupancyGrid

    from bridgeos_agent.usecases.ros2.node import latched

    nodes2, listener = ros2
    config = mixed_skill()
    skill = config["skill_id"]
    assert {c["ros"] for c in config["components"].values()} == {True, 2}
    placed = {cid: "cloud" if cid == "planner" else "robot" for cid in config["components"]}
    router = await make_router(config, ros_master.uri, **placed)
    assert router.ros_on and router.ros2_on

    def ns(component: str) -> str:
        return instance_namespace(skill, component, placed[component])

    # ROS 1 navigation in the room, ROS 2 mapping of the room.
    nodes.start("sim", "sim", "--world", "room", "--speed", "1.0", namespace=ns("sim"))
    nodes.start("map-server", "map-server", "--world", "room", "--period", "2", namespace=ns("map-server"))
    nodes.start("planner", "planner", namespace=ns("planner"))
    nodes.start("mover", "mover", "--world", "room", "--loops", "1", "--tolerance", "0.2", namespace=ns("mover"))
    nodes2.start("sim2", "sim", "--world", "room", namespace=ns("sim2"))
    nodes2.start("odometry", "odometry", "--world", "room", namespace=ns("odometry"))
    nodes2.start("mapping", "mapping", "--world", "room", "--period", "0.5", namespace=ns("mapping"))
    nodes2.start(
        "controller", "controller", "--world", "room", "--speed", "1.0", "--loops", "1", namespace=ns("controller")
    )

    path = await asyncio.to_thread(nodes.probe, PATH_PROBE, "60", timeout=90)
    assert len(path) >= 3, path
    await asyncio.to_thread(nodes2.wait_for, "controller", r"metric tour_duration_s=[\d.]+", 60)
    # The ROS 2 map on its instance name (the mixed Skill routes ROS 1's /map): built from routed scans and odometry.
    probe = listener("/")
    built = await asyncio.to_thread(
        probe.wait_for, OccupancyGrid, ns("mapping") + "/map", latched(), lambda m: True, 20
    )
    truth = get_world("room").occupancy(0.1)
    values = np.asarray(built.data, dtype=np.int8).reshape(built.info.height, built.info.width)
    score = map_agreement(values, truth)
    assert score["observed"] > 0.6 and score["agreement"] > 0.9, score
    await asyncio.to_thread(nodes.wait_for, "mover", r"metric tour_duration_s=[\d.]+", 60)
    stats = router.statistics()
    assert stats["/scan"]["messages"] > 0 and stats["/odom"]["messages"] > 0, stats  # ROS 2 routes
    assert stats["/path"]["messages"] > 0, stats  # a ROS 1 route
