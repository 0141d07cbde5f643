"""The use-case Skills' ROS nodes, run by `bridgeos-usecase` against a private rosmaster.

Real rospy processes talk over real topics; only the robot's motors and sensors are
simulated (the `sim` node and the camera). Every node runs in a namespace, as the Skill
Router runs component instances, to prove the nodes use relative names.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import subprocess
import threading
import uuid
from collections.abc import Collection, Iterator
from typing import Any

import numpy as np
import pytest

from bridgeos_agent.componentsapi import ComponentsAPI, MetricStore
from bridgeos_agent.skillconfig import SkillConfig, load_sample_skill_config
from bridgeos_agent.usecases.occupancy import map_agreement
from bridgeos_agent.usecases.planning import segment_free
from bridgeos_agent.usecases.world import get_world
from tests.usecases.conftest import Nodes

pytestmark = pytest.mark.ros

ROS_IMAGE = "bridgeos/ros:noetic"

PEOPLE_PROBE = """
import json, sys, rospy
from geometry_msgs.msg import PoseArray
rospy.init_node("probe", anonymous=True, disable_signals=True)
msg = rospy.wait_for_message("people", PoseArray, timeout=float(sys.argv[1]))
print(json.dumps([[p.position.x, p.position.y] for p in msg.poses]))
"""

PATH_PROBE = """
import json, sys, rospy
from nav_msgs.msg import Path
rospy.init_node("probe", anonymous=True, disable_signals=True)
msg = rospy.wait_for_message("path", Path, timeout=float(sys.argv[1]))
print(json.dumps([[p.pose.position.x, p.pose.position.y] for p in msg.poses]))
"""

POSE_PROBE = """
import json, sys, rospy
from geometry_msgs.msg import PoseStamped
rospy.init_node("probe", anonymous=True, disable_signals=True)
msg = rospy.wait_for_message("pose", PoseStamped, timeout=float(sys.argv[1]))
print(json.dumps([msg.pose.position.x, msg.pose.position.y]))
"""

MAP_PROBE = """
import json, sys, rospy
from nav_msgs.msg import OccupancyGrid
rospy.init_node("probe", anonymous=True, disable_signals=True)
msg = rospy.wait_for_message("map", OccupancyGrid, timeout=float(sys.argv[1]))
print(json.dumps({"width": msg.info.width, "height": msg.info.height, "resolution": msg.info.resolution,
                  "data": list(msg.data)}))
"""


class SkillView:
    """Play a Skill's manager for the Components API: a real Skill config and a real MetricStore."""

    def __init__(self, config: SkillConfig) -> None:
        self.config = config
        self.store = MetricStore()

    def components(self) -> list[dict[str, Any]]:
        return [self.component(cid) for cid in self.config.components]

    def component(self, component_id: str) -> dict[str, Any]:
        component = self.config.components[component_id]
        return {"id": component_id, "name": component.name, "location": component.location}

    def locations(self) -> dict[str, str | None]:
        return dict.fromkeys(self.config.components, "robot")

    def recommend(self, component_id: str, location: str) -> None:
        raise ValueError("no recommendations in this test")

    def latest_metrics(self, names: Collection[str] | None, component: str | None) -> list[dict[str, Any]]:
        return self.store.latest(names, component)

    def publish(self, points: list[dict[str, Any]]) -> int:
        return self.store.publish(points)


@pytest.fixture
def components_api() -> Iterator[tuple[str, SkillView]]:
    """Serve the real Components API for the people-detection Skill on a loop of its own."""
    view = SkillView(load_sample_skill_config("people_detection"))
    api = ComponentsAPI(view)
    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=loop.run_forever, daemon=True)
    thread.start()
    url = asyncio.run_coroutine_threadsafe(api.start(), loop).result(timeout=30)
    try:
        yield url, view
    finally:
        asyncio.run_coroutine_threadsafe(api.stop(), loop).result(timeout=30)
        loop.call_soon_threadsafe(loop.stop)
        thread.join(timeout=10)
        loop.close()


def test_people_detection_finds_the_people_placed_in_the_scene(nodes: Nodes, components_api) -> None:
    url, view = components_api
    people = [(2.5, 0.8), (4.0, -1.0), (5.5, 0.6)]
    ns = "/bridgeos/people-detection/test/robot"
    spots = ";".join(f"{x},{y}" for x, y in people)
    nodes.start(
        "pointcloud", "pointcloud", "--width", "320", "--height", "240", "--rate", "2", "--people", spots, namespace=ns
    )
    nodes.start("sampler", "sampler", "--voxel", "0.05", namespace=ns)
    api_env = {"BRIDGEOS_MANAGER_URL": url, "BRIDGEOS_COMPONENT": "detector", "BRIDGEOS_LOCATION": "robot"}
    nodes.start("detector", "detector", namespace=ns, **api_env)

    found = nodes.probe(PEOPLE_PROBE, "60", timeout=90, namespace=ns)

    assert len(found) == len(people), f"detected {found}, placed {people}\n{nodes.all_logs()}"
    for x, y in people:
        # The camera sees a person's front: the centroid sits a little nearer than the centre.
        nearest = min(math.dist((x, y), tuple(d)) for d in found)
        assert nearest < 0.35, f"no detection near {(x, y)}: {found}"
    nodes.wait_for("detector", r"metric pointcloud_processing_ms=\d", timeout=30)
    deadline = 60
    for _ in range(deadline * 5):
        points = view.latest_metrics(["pointcloud_processing_ms"], "detector")
        if points:
            break
        threading.Event().wait(0.2)
    assert points, f"the detector posted no pointcloud_processing_ms to the Components API\n{nodes.all_logs()}"
    assert points[0]["value"] > 0
    assert points[0]["labels"]["location"] == "robot"


def test_navigation_plans_around_obstacles_and_the_robot_reaches_its_goal(nodes: Nodes) -> None:
    world = get_world("room")
    grid, occupied = world.grid(0.1), world.occupancy(0.1)
    goal = world.goals[0]
    ns = "/bridgeos/navigation/test"
    nodes.start("sim", "sim", "--world", "room", "--speed", "1.0", namespace=ns)
    nodes.start("map-server", "map-server", "--world", "room", "--period", "2", namespace=ns)
    nodes.start("planner", "planner", namespace=ns)
    nodes.start("mover", "mover", "--world", "room", "--loops", "1", "--tolerance", "0.2", namespace=ns)

    path = nodes.probe(PATH_PROBE, "90", timeout=120, namespace=ns)

    assert len(path) >= 3, f"the partition stands between start and goal, so the path bends: {path}"
    assert math.dist(path[0], world.start[:2]) < 0.15 and math.dist(path[-1], goal) < 1e-6
    for a, b in itertools.pairwise(path):
        assert segment_free(occupied, grid, tuple(a), tuple(b)), f"segment {a} -> {b} crosses an obstacle"
    duration = float(nodes.wait_for("mover", r"metric tour_duration_s=([\d.]+)", timeout=120).group(1))
    assert duration > 0
    final = nodes.probe(POSE_PROBE, "30", timeout=60, namespace=ns)
    assert math.dist(final, goal) < 0.3, f"robot stopped at {final}, goal {goal}\n{nodes.all_logs()}"


def test_mapping_builds_a_map_that_matches_the_world(nodes: Nodes) -> None:
    world = get_world("room")
    truth = world.occupancy(0.1)
    ns = "/bridgeos/mapping/test"
    nodes.start("sim", "sim", "--world", "room", namespace=ns)
    nodes.start("odometry", "odometry", "--world", "room", namespace=ns)
    nodes.start("mapping", "mapping", "--world", "room", "--period", "0.5", namespace=ns)
    nodes.start("controller", "controller", "--world", "room", "--speed", "1.0", "--loops", "1", namespace=ns)

    duration = float(nodes.wait_for("controller", r"metric tour_duration_s=([\d.]+)", timeout=150).group(1))
    assert duration > 0
    built = nodes.probe(MAP_PROBE, "30", timeout=60, namespace=ns)

    assert (built["width"], built["height"]) == (truth.shape[1], truth.shape[0])
    values = np.asarray(built["data"], dtype=np.int8).reshape(built["height"], built["width"])
    score = map_agreement(values, truth)
    assert score["observed"] > 0.6, score
    assert score["agreement"] > 0.9, score
    assert score["occupied_precision"] > 0.9, score
    loss = nodes.wait_for("mapping", r"metric message_loss_pct=([\d.]+) topic=scan", timeout=30)
    assert float(loss.group(1)) < 5.0


@pytest.mark.docker
def test_a_node_runs_in_the_ros_image_and_talks_to_host_nodes(nodes: Nodes) -> None:
    """The bridgeos/ros image carries the nodes: its map server feeds a planner on the host."""
    found = subprocess.run(
        ["docker", "run", "--rm", ROS_IMAGE, "sh", "-c", "command -v bridgeos-usecase"],
        capture_output=True,
        timeout=120,
    )
    if found.returncode != 0:
        pytest.fail(
            f"image {ROS_IMAGE} is missing or lacks the use-case nodes: run `scripts/services.sh images`", pytrace=False
        )
    world = get_world("room")
    ns = "/bridgeos/navigation/docker"
    name = f"usecases-map-server-{uuid.uuid4().hex[:8]}"
    env = {"ROS_MASTER_URI": nodes.master.uri, "ROS_IP": "127.0.0.1", "ROS_NAMESPACE": ns}
    try:
        subprocess.run(
            [
                "docker",
                "run",
                "-d",
                "--rm",
                "--init",
                "--network",
                "host",
                "--name",
                name,
                *(f"--env={k}={v}" for k, v in env.items()),
                ROS_IMAGE,
                "bridgeos-usecase",
                "map-server",
                "--world",
                "room",
                "--period",
                "1",
            ],
            check=True,
            capture_output=True,
            timeout=120,
        )
        nodes.start("planner", "planner", namespace=ns)
        nodes.start("sim", "sim", "--world", "room", namespace=ns)
        nodes.start("mover", "mover", "--world", "room", "--loops", "1", namespace=ns)
        path = nodes.probe(PATH_PROBE, "90", timeout=120, namespace=ns)
        assert len(path) >= 3 and math.dist(path[-1], world.goals[0]) < 1e-6, path
    except BaseException:
        logs = subprocess.run(["docker", "logs", name], capture_output=True, text=True, timeout=60)
        print(f"container logs:\n{logs.stdout}{logs.stderr}")
        raise
    finally:
        subprocess.run(["docker", "rm", "-f", name], capture_output=True, timeout=60)
