"""A ROS 2 cloud copy on Docker Swarm: in bridgeos/ros2:jazzy, a client of its robot's discovery server.

Both an ad-hoc rclpy talker and a use case's own node (``bridgeos-usecase2 pointcloud``, the command
the ROS 2 use-case Skills' cloud copies run) run from the image.

The robot authenticates with its ROS 2 graph; the cloud's worker runs the robot's Fast DDS
discovery server as a host-networked Swarm service of the ROS 2 image, then the copy (an rclpy
talker, no image named: the ROS 2 image by default) as another; an rclpy listener on the host,
a client of the same server, hears the copy under the namespace the router assigned.
"""

from __future__ import annotations

import asyncio
import random
import subprocess
from collections.abc import Iterator

import pytest

import docker
from bridgeos_agent.protocol import Event
from bridgeos_agent.rosnames import instance_namespace
from bridgeos_agent.skillconfig import parse_skill_config
from skills.cloud.runtime import object_name
from tests.agent.conftest import make_robot
from tests.cloud.wsutil import robot_login
from tests.conftest import eventually

from .conftest import make_stack
from .test_ros2_discovery import (
    DOMAIN,
    GRAPH,
    LISTENER,
    TALKER,
    _copy_running,
    _copy_stopped,
    heard,
    node,
    server_status,
    stop,
)

IMAGE = "bridgeos/ros2:jazzy"
SKILL = "ros2swarm"


def _image_missing() -> str | None:
    found = subprocess.run(["docker", "image", "inspect", IMAGE], capture_output=True, check=False)
    return None if found.returncode == 0 else f"no {IMAGE} image: docker/build-images.sh ros2"


pytestmark = [
    pytest.mark.django_db(transaction=True),
    pytest.mark.docker,
    pytest.mark.timeout(180),
    pytest.mark.usefixtures("robots_disconnect_before_flush"),
    pytest.mark.skipif(_image_missing() is not None, reason=str(_image_missing())),
]


@pytest.fixture(scope="module")
def stack(django_db_setup, django_db_blocker, tmp_path_factory) -> Iterator:
    from django.conf import settings

    low = random.randrange(47000, 49000, 20)
    ports = f"{low}-{low + 19}"
    saved = settings.BRIDGEOS["CLOUD_ROS2_DISCOVERY_PORTS"]
    settings.BRIDGEOS["CLOUD_ROS2_DISCOVERY_PORTS"] = ports
    try:
        yield from make_stack("swarm", tmp_path_factory.mktemp("ros2swarm"), BRIDGEOS_CLOUD_ROS2_DISCOVERY_PORTS=ports)
    finally:
        settings.BRIDGEOS["CLOUD_ROS2_DISCOVERY_PORTS"] = saved


async def test_a_ros2_cloud_copy_in_the_ros2_image_talks_through_its_robots_discovery_server(stack):
    config = {
        "skill": "ROS 2 on Swarm",
        "skill_id": SKILL,
        "components": {
            "talker": {"name": "Talker", "location": "cloud", "ros": 2, "cloud": {"command": ["python3", "-c", TALKER]}}
        },
    }
    token, _ = await make_robot("r2-swarm", skill=parse_skill_config(config).model_dump(mode="json"))
    link, success = await robot_login(stack, "r2-swarm", token, ros2=GRAPH)
    address = success["ros2_discovery_server"]
    namespace = instance_namespace(SKILL, "talker", "cloud")
    listener = None
    try:
        await eventually(lambda: _is_running("r2-swarm"), timeout=90, what="the discovery server service running")
        await link.send(Event.COMPONENT_START, {"skill": SKILL, "component": "talker", "location": "cloud"})
        await eventually(lambda: _copy_running("r2-swarm"), timeout=90, what="the copy's service running")
        client = docker.from_env()
        service = client.services.get(object_name("r2-swarm", SKILL, "talker"))
        spec = service.attrs["Spec"]["TaskTemplate"]["ContainerSpec"]
        env = dict(item.split("=", 1) for item in spec["Env"])
        assert spec["Image"].startswith(IMAGE)
        assert env["ROS_DISCOVERY_SERVER"] == address and env["ROS_DOMAIN_ID"] == str(DOMAIN)
        assert env["ROS_NAMESPACE"] == namespace and "ROS_MASTER_URI" not in env
        assert spec["Args"][-3:] == ["--ros-args", "-r", f"__ns:={namespace}"]
        # Shared memory does not cross the container's boundary: its Fast DDS uses UDP only.
        assert env["FASTDDS_BUILTIN_TRANSPORTS"] == "UDPv4"

        # The copy's rclpy may still be starting in its container: listen again, a few times at most.
        for _ in range(3):
            listener = node(LISTENER, [f"{namespace}/chatter", "12"], address)
            if await asyncio.to_thread(heard, listener) > 0:
                break
        else:
            raise AssertionError("the host listener never heard the cloud copy through the robot's discovery server")
    finally:
        if listener is not None:
            stop(listener)
        await link.send(Event.COMPONENT_STOP, {"skill": SKILL, "component": "talker", "location": "cloud"})
        # The stop done before the tables are flushed: the worker's writes would deadlock with the flush.
        await eventually(lambda: _copy_stopped("r2-swarm"), timeout=60, what="the cloud copy stopped")
        await link.close()


async def _is_running(robot_id: str) -> bool:
    return (await server_status(robot_id)) == "running"


# Counts the PointCloud2 messages of a topic for a while and prints how many, with the first one's size.
CLOUD_LISTENER = """
import sys, time, rclpy
from sensor_msgs.msg import PointCloud2
rclpy.init()
node = rclpy.create_node("cloud_listener")
heard = []
node.create_subscription(PointCloud2, sys.argv[1], lambda m: heard.append(m.width * m.height), 10)
end = time.monotonic() + float(sys.argv[2])
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
print(len(heard), heard[:1], flush=True)
"""


async def test_a_ros2_use_case_node_runs_as_a_swarm_cloud_copy_from_the_ros2_image(stack):
    command = ["bridgeos-usecase2", "pointcloud", "--width", "32", "--height", "24", "--rate", "5"]
    config = {
        "skill": "ROS 2 use case on Swarm",
        "skill_id": "usecase2swarm",
        "components": {
            "pointcloud": {"name": "Pointcloud", "location": "cloud", "ros": 2, "cloud": {"command": command}}
        },
    }
    token, _ = await make_robot("r2-usecase", skill=parse_skill_config(config).model_dump(mode="json"))
    link, success = await robot_login(stack, "r2-usecase", token, ros2=GRAPH)
    address = success["ros2_discovery_server"]
    namespace = instance_namespace("usecase2swarm", "pointcloud", "cloud")
    try:
        await eventually(lambda: _is_running("r2-usecase"), timeout=90, what="the discovery server service running")
        await link.send(
            Event.COMPONENT_START, {"skill": "usecase2swarm", "component": "pointcloud", "location": "cloud"}
        )
        await eventually(lambda: _copy_running("r2-usecase"), timeout=90, what="the use case's copy running")
        spec = docker.from_env().services.get(object_name("r2-usecase", "usecase2swarm", "pointcloud"))
        assert spec.attrs["Spec"]["TaskTemplate"]["ContainerSpec"]["Image"].startswith(IMAGE)
        for _ in range(3):  # its rclpy may still be starting in the container
            listener = node(CLOUD_LISTENER, [f"{namespace}/pointcloud", "12"], address)
            out, _ = await asyncio.to_thread(listener.communicate, timeout=60)
            count = out.strip().splitlines()[-1].split(" ", 1)[0] if out.strip() else ""
            assert count.isdigit(), f"the listener failed:\n{out[-2000:]}"
            if int(count) > 0:
                assert "[768]" in out  # 32 x 24 points: the node's own cloud, rendered in the container
                break
        else:
            raise AssertionError("no point cloud from the use case's cloud copy reached the host")
    finally:
        await link.send(
            Event.COMPONENT_STOP, {"skill": "usecase2swarm", "component": "pointcloud", "location": "cloud"}
        )
        await eventually(lambda: _copy_stopped("r2-usecase"), timeout=60, what="the cloud copy stopped")
        await link.close()
