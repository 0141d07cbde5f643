"""The use-case Skills' ROS 2 nodes (``bridgeos-usecase2``): real rclpy processes on real DDS topics.

Each test runs one Skill's nodes in a namespace of its own (as the Skill Router runs instances:
``--ros-args -r __ns:=...`` for most, ``ROS_NAMESPACE`` for one) and checks what the algorithm
published with an rclpy listener in this process. DDS stays on loopback
(ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST) in a domain of its own (BRIDGEOS_TEST_ROS2_DOMAIN, 46).
"""

from __future__ import annotations

import itertools
import math
import re
import subprocess
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from bridgeos_agent.usecases.occupancy import map_agreement
from bridgeos_agent.usecases.planning import segment_free
from bridgeos_agent.usecases.world import get_world
from tests.usecases.ros2help import Ros2Nodes, usecase2_command


def unique(skill: str) -> str:
    return f"/bridgeos/{skill}/t{uuid.uuid4().hex[:8]}/robot"


def latched() -> Any:
    from bridgeos_agent.usecases.ros2.node import latched as profile

    return profile()


@pytest.mark.timeout(90)
def test_ros2_people_detection_finds_the_people_placed_in_the_scene(ros2) -> None:
    from geometry_msgs.msg import PoseArray

    nodes, listener = ros2
    began = time.monotonic()
    people = [(2.5, 0.8), (4.0, -1.0), (5.5, 0.6)]
    ns = unique("people_detection")
    spots = ";".join(f"{x},{y}" for x, y in people)
    nodes.start(
        "pointcloud", "pointcloud", "--width", "320", "--height", "240", "--rate", "2", "--people", spots, namespace=ns
    )
    nodes.start("sampler", "sampler", "--voxel", "0.05", namespace=ns)
    nodes.start("detector", "detector", namespace=ns, remap=False)

    found = listener(ns).wait_for(PoseArray, "people", 10, lambda m: len(m.poses) > 0, timeout=45)

    spotted = [(p.position.x, p.position.y) for p in found.poses]
    assert len(spotted) == len(people), f"detected {spotted}, placed {people}\n{nodes.all_logs()}"
    for x, y in people:
        # The camera sees a person's front: the centroid sits a little nearer than the centre.
        assert min(math.dist((x, y), d) for d in spotted) < 0.35, f"no detection near {(x, y)}: {spotted}"
    assert found.header.frame_id == "camera"  # the camera's header, carried through sampler and detector
    latency = float(nodes.wait_for("detector", r"metric pointcloud_processing_ms=([\d.]+)", timeout=10).group(1))
    assert 0 < latency < 10_000
    assert re.search(r"\[sampler\] metric sampling_ms=[\d.]+ points=\d+", nodes.log("sampler"))
    assert time.monotonic() - began < 60


@pytest.mark.timeout(90)
def test_ros2_navigation_plans_around_obstacles_and_the_robot_reaches_its_goal(ros2) -> None:
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import Path as PathMsg

    from bridgeos_agent.usecases.ros2.node import reliable

    nodes, listener = ros2
    began = time.monotonic()
    world = get_world("room")
    grid, occupied = world.grid(0.1), world.occupancy(0.1)
    goal = world.goals[0]
    ns = unique("navigation")
    nodes.start("sim", "sim", "--world", "room", "--speed", "1.0", namespace=ns)
    nodes.start("map-server", "map-server", "--world", "room", "--period", "2", namespace=ns)
    nodes.start("planner", "planner", namespace=ns)
    nodes.start("mover", "mover", "--world", "room", "--loops", "1", "--tolerance", "0.2", namespace=ns)
    probe = listener(ns)

    # Transient-local: the plan reaches a listener that subscribes after it was published.
    plan = probe.wait_for(PathMsg, "path", latched(), lambda m: len(m.poses) > 0, timeout=40)

    path = [(p.pose.position.x, p.pose.position.y) for p in plan.poses]
    assert len(path) >= 3, f"the partition stands between start and goal, so the path bends: {path}"
    assert math.dist(path[0], world.start[:2]) < 0.15 and math.dist(path[-1], goal) < 1e-6
    for a, b in itertools.pairwise(path):
        assert segment_free(occupied, grid, a, b), f"segment {a} -> {b} crosses an obstacle"
    duration = float(nodes.wait_for("mover", r"metric tour_duration_s=([\d.]+)", timeout=40).group(1))
    assert duration > 0
    final = probe.wait_for(PoseStamped, "pose", reliable(10), lambda m: True, timeout=10)
    assert math.dist((final.pose.position.x, final.pose.position.y), goal) < 0.3, nodes.all_logs()
    assert time.monotonic() - began < 60


@pytest.mark.timeout(90)
def test_ros2_mapping_builds_a_map_that_matches_the_world(ros2) -> None:
    from nav_msgs.msg import OccupancyGrid

    nodes, listener = ros2
    began = time.monotonic()
    world = get_world("room")
    truth = world.occupancy(0.1)
    ns = unique("mapping")
    nodes.start("sim", "sim", "--world", "room", namespace=ns)
    nodes.start("odometry", "odometry", "--world", "room", namespace=ns)
    nodes.start("mapping", "mapping", "--world", "room", "--period", "0.5", "--report-period", "1", namespace=ns)
    nodes.start("controller", "controller", "--world", "room", "--speed", "1.0", "--loops", "1", namespace=ns)

    duration = float(nodes.wait_for("controller", r"metric tour_duration_s=([\d.]+)", timeout=45).group(1))
    assert duration > 0
    built = listener(ns).wait_for(OccupancyGrid, "map", latched(), lambda m: True, timeout=10)

    assert (built.info.width, built.info.height) == (truth.shape[1], truth.shape[0])
    values = np.asarray(built.data, dtype=np.int8).reshape(built.info.height, built.info.width)
    score = map_agreement(values, truth)
    assert score["observed"] > 0.6, score
    assert score["agreement"] > 0.9, score
    assert score["occupied_precision"] > 0.9, score
    # Loss from the middleware's publication sequence numbers (ROS 2 headers have no seq).
    loss = nodes.wait_for("mapping", r"metric message_loss_pct=([\d.]+) topic=scan", timeout=10)
    assert float(loss.group(1)) < 5.0
    assert time.monotonic() - began < 60


def test_ros2_nodes_refuse_bad_arguments_before_touching_dds(tmp_path: Path) -> None:
    """A bad argument is a clear usage error and exits at once, ROS args or not."""
    nodes = Ros2Nodes(tmp_path)
    done = subprocess.run(
        [*usecase2_command(), "sim", "--world", "mars", "--ros-args", "-r", "__ns:=/x"],
        env=nodes.env(),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 2 and "unknown world 'mars'" in done.stderr, done.stderr
    unknown = subprocess.run(
        [*usecase2_command(), "teleport"], env=nodes.env(), capture_output=True, text=True, timeout=60
    )
    assert unknown.returncode == 2 and "usage: bridgeos-usecase2 NODE" in unknown.stderr
