"""The cloud side of ROS 2: a Fast DDS discovery server per robot, and ROS 2 cloud copies in their robot's graph.

Real parts throughout: daphne and a Celery worker of a test cloud of their own (process runtime),
robots authenticating over real sockets with their ROS 2 graph, the real ``fast-discovery-server``
of the ROS 2 wheels, and rclpy talkers and listeners as separate processes. Every node runs in
ROS_DOMAIN_ID 45 (this suite's own) and discovers peers only through a discovery server, so no
other test run's nodes are seen.
"""

from __future__ import annotations

import asyncio
import json
import os
import random
import subprocess
import sys
from collections.abc import Iterator

import httpx
import psutil
import pytest
import websockets
from asgiref.sync import sync_to_async

from bridgeos_agent import protocol
from bridgeos_agent.protocol import Event
from bridgeos_agent.ros2graph import namespace_arguments, rclpy_missing
from bridgeos_agent.rosnames import instance_namespace
from bridgeos_agent.skillconfig import parse_skill_config
from robots.models import Robot
from skills.cloud.runtime import KIND_ROS2_DISCOVERY
from skills.models import CloudInstance, RobotCloud
from tests.agent.conftest import make_robot
from tests.cloud.wsutil import robot_login
from tests.conftest import eventually

from .conftest import make_stack, observe_async

pytestmark = [
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(240),
    pytest.mark.usefixtures("robots_disconnect_before_flush"),
    pytest.mark.skipif(rclpy_missing() is not None, reason=str(rclpy_missing())),
]

DOMAIN = 45
GRAPH = {"domain_id": DOMAIN, "rmw": "rmw_fastrtps_cpp", "discovery_range": "LOCALHOST"}
SKILL = "ros2cloud"
# The cloud's venv (the worker's interpreter, with the ROS 2 wheels), however its path is spelled.
VENV_BIN = os.path.realpath(os.path.dirname(sys.executable))
# The nodes: a talker publishing "<TAG>:<n>" on its topic, and a listener printing how many it heard.
TALKER = """
import os, sys, rclpy
from rclpy.executors import ExternalShutdownException
from std_msgs.msg import String
rclpy.init(args=sys.argv)
node = rclpy.create_node("talker")
pub = node.create_publisher(String, "chatter", 10)
n = 0
try:
    while rclpy.ok():
        pub.publish(String(data=f"{os.environ.get('TAG', '')}:{n}"))
        n += 1
        rclpy.spin_once(node, timeout_sec=0.05)
except (KeyboardInterrupt, ExternalShutdownException):
    pass
"""
LISTENER = """
import sys, time, rclpy
from std_msgs.msg import String
rclpy.init()
node = rclpy.create_node("listener")
heard = []
node.create_subscription(String, sys.argv[1], lambda m: heard.append(m.data), 10)
print("ready", flush=True)
end = time.monotonic() + float(sys.argv[2])
while time.monotonic() < end:
    rclpy.spin_once(node, timeout_sec=0.05)
print(len(heard), " ".join(heard[:3]), flush=True)
"""


@pytest.fixture(scope="module")
def stack(django_db_setup, django_db_blocker, tmp_path_factory) -> Iterator:
    from django.conf import settings

    low = random.randrange(43000, 47000, 20)
    ports = f"{low}-{low + 19}"
    saved = settings.BRIDGEOS["CLOUD_ROS2_DISCOVERY_PORTS"]
    settings.BRIDGEOS["CLOUD_ROS2_DISCOVERY_PORTS"] = ports
    try:
        yield from make_stack("process", tmp_path_factory.mktemp("ros2"), BRIDGEOS_CLOUD_ROS2_DISCOVERY_PORTS=ports)
    finally:
        settings.BRIDGEOS["CLOUD_ROS2_DISCOVERY_PORTS"] = saved


# --------------------------------------------------------------------------- helpers


def node(code: str, args: list[str], server: str, **env: str) -> subprocess.Popen:
    """Start an rclpy node in a process of its own, a client of the discovery server ``server`` only."""
    clean = {k: v for k, v in os.environ.items() if not k.startswith(("ROS_", "RMW_"))}
    clean.update(ROS_DOMAIN_ID=str(DOMAIN), RMW_IMPLEMENTATION="rmw_fastrtps_cpp", ROS_DISCOVERY_SERVER=server)
    return subprocess.Popen(
        [sys.executable, "-c", code, *args],
        env={**clean, **env},
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )


def heard(listener: subprocess.Popen, timeout: float = 60) -> int:
    """Wait for a listener to finish and return how many messages it heard."""
    out, _ = listener.communicate(timeout=timeout)
    last = out.strip().splitlines()[-1] if out.strip() else ""
    assert last.split(" ", 1)[0].isdigit(), f"the listener failed:\n{out[-2000:]}"
    return int(last.split(" ", 1)[0])


def stop(*processes: subprocess.Popen) -> None:
    for process in processes:
        if process.poll() is None:
            process.terminate()
            try:
                process.wait(10)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(5)


@sync_to_async
def cloud_row(robot_id: str) -> RobotCloud | None:
    return RobotCloud.objects.filter(robot_id=robot_id).first()


async def server_status(robot_id: str) -> str | None:
    row = await cloud_row(robot_id)
    return row.ros2_discovery_status if row else None


async def servers_of(stack, robot_id: str) -> list:
    return [o for o in await observe_async(stack.runtime) if o.robot == robot_id and o.kind == KIND_ROS2_DISCOVERY]


def port_of(address: str) -> int:
    host, _, port = address.rpartition(":")
    assert host == "127.0.0.1", address
    return int(port)


# --------------------------------------------------------------------------- tests


async def test_a_robot_logging_in_with_ros2_gets_a_running_discovery_server_and_its_address(stack):
    from django.conf import settings

    token, api_token = await make_robot("r2-one")
    link, success = await robot_login(stack, "r2-one", token, ros2=GRAPH)
    address = success["ros2_discovery_server"]
    low, high = (int(p) for p in settings.BRIDGEOS["CLOUD_ROS2_DISCOVERY_PORTS"].split("-"))
    assert low <= port_of(address) <= high
    await eventually(lambda: _is(server_status("r2-one"), "running"), timeout=60, what="the server running")
    [server] = await servers_of(stack, "r2-one")
    rss_mb = psutil.Process(server.id).memory_info().rss / 2**20
    print(f"discovery server RSS: {rss_mb:.1f} MB")
    assert rss_mb < 64

    # A real discovery server: two clients of it find each other and talk.
    listener = node(LISTENER, ["/chatter", "12"], address)
    talker = node(TALKER, [], address, TAG="one")
    try:
        assert await asyncio.to_thread(heard, listener) > 0
    finally:
        stop(talker, listener)

    # The owner sees the graph in the API (info and the list's fields); another user sees no robot.
    expected = {**GRAPH, "static_peers": [], "discovery_server": None, "cloud_discovery_server": address}
    _, other_token = await make_robot("r2-other")
    async with httpx.AsyncClient(base_url=stack.url, timeout=30) as api:
        owner = {"Authorization": f"Token {api_token}"}
        info = (await api.get("/api/robot/r2-one/info", headers=owner)).json()
        assert info["ros2"] == expected
        listed = (await api.get("/api/robot", params={"fields": "id,ros2"}, headers=owner)).json()
        assert listed == [{"id": "r2-one", "ros2": expected}]
        stranger = {"Authorization": f"Token {other_token}"}
        assert (await api.get("/api/robot/r2-one/info", headers=stranger)).status_code == 404
        assert [r["id"] for r in (await api.get("/api/robot", headers=stranger)).json()] == ["r2-other"]

    # Back without ROS 2: no server named, the one it had is stopped, the API shows no graph.
    await link.close()
    link, success = await robot_login(stack, "r2-one", token)
    try:
        assert "ros2_discovery_server" not in success
        await eventually(lambda: _is(server_status("r2-one"), "stopped"), timeout=60, what="the server stopped")
        assert await servers_of(stack, "r2-one") == []
        assert (await sync_to_async(Robot.objects.get)(id="r2-one")).ros2 is None
        # The port stays the robot's: it gets the same address when it comes back with ROS 2.
        await link.close()
        link, success = await robot_login(stack, "r2-one", token, ros2=GRAPH)
        assert success["ros2_discovery_server"] == address
        await eventually(lambda: _is(server_status("r2-one"), "running"), timeout=60, what="the server back")
    finally:
        await link.close()


async def test_two_robots_cloud_graphs_are_isolated_on_one_host_and_domain_and_go_with_their_robots(stack):
    token_a, _ = await make_robot("r2-a")
    token_b, _ = await make_robot("r2-b")
    link_a, success_a = await robot_login(stack, "r2-a", token_a, ros2=GRAPH)
    link_b, success_b = await robot_login(stack, "r2-b", token_b, ros2=GRAPH)
    server_a, server_b = success_a["ros2_discovery_server"], success_b["ros2_discovery_server"]
    assert server_a != server_b
    for robot_id in ("r2-a", "r2-b"):
        await eventually(lambda r=robot_id: _is(server_status(r), "running"), timeout=60, what=f"{robot_id}'s server")

    # Same host, same ROS_DOMAIN_ID, same topic: only robot A's graph hears robot A's talker.
    in_a = node(LISTENER, ["/chatter", "12"], server_a)
    in_b = node(LISTENER, ["/chatter", "12"], server_b)
    talker = node(TALKER, [], server_a, TAG="a")
    try:
        heard_a, heard_b = await asyncio.gather(asyncio.to_thread(heard, in_a), asyncio.to_thread(heard, in_b))
    finally:
        stop(talker, in_a, in_b)
    assert heard_a > 0
    assert heard_b == 0

    # A deleted robot's server goes: the reconciler removes what no robot holds any more.
    await link_a.close()
    await link_b.close()
    await eventually(lambda: _disconnected("r2-a", "r2-b"), timeout=30, what="the robots gone")
    await sync_to_async(lambda: Robot.objects.filter(id__in=["r2-a", "r2-b"]).delete())()
    await asyncio.to_thread(stack.reconcile)
    await eventually(lambda: _no_servers(stack, "r2-a", "r2-b"), timeout=60, what="the deleted robots' servers gone")


async def test_a_ros2_cloud_copy_runs_in_its_robots_graph_with_its_namespace(stack):
    from skills.cloud.orchestration import cloud_spec, instance_row

    code = TALKER
    config = {
        "skill": "ROS 2 cloud",
        "skill_id": SKILL,
        "components": {
            "talker": {
                "name": "Talker",
                "location": "cloud",
                "ros": 2,
                "cloud": {"command": ["python3", "-c", code]},
            }
        },
    }
    config = parse_skill_config(config).model_dump(mode="json")
    token, _ = await make_robot("r2-copy", skill=config)
    link, success = await robot_login(stack, "r2-copy", token, ros2=GRAPH)
    address = success["ros2_discovery_server"]
    namespace = instance_namespace(SKILL, "talker", "cloud")
    listener = None
    try:
        await eventually(lambda: _is(server_status("r2-copy"), "running"), timeout=60, what="the server running")
        await link.send(Event.COMPONENT_START, {"skill": SKILL, "component": "talker", "location": "cloud"})
        await eventually(lambda: _copy_running("r2-copy"), timeout=90, what="the cloud copy running")

        # Its launch: the robot's graph, its server, its namespace (env and --ros-args), and no ROS master.
        instance = await sync_to_async(CloudInstance.objects.get)(component__skill__robot_id="r2-copy")
        spec = await sync_to_async(lambda: cloud_spec(instance_row(instance.pk)))()
        assert spec.env["ROS_DOMAIN_ID"] == str(DOMAIN)
        assert spec.env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
        assert spec.env["ROS_DISCOVERY_SERVER"] == address
        assert spec.env["ROS_NAMESPACE"] == namespace
        assert "ROS_MASTER_URI" not in spec.env
        assert spec.launch.command == ["python3", "-c", code, *namespace_arguments(namespace)]

        # The process really runs so, with the cloud venv's python3 (the one with rclpy).
        pid = int(instance.container["id"])
        process = psutil.Process(pid)
        # Read once it has exec'd the command: before that, /proc shows the forking worker's env.
        await eventually(lambda: process.cmdline()[-3:] == namespace_arguments(namespace), what="the command exec'd")
        env = process.environ()
        launched = {k: v for k, v in env.items() if k.startswith(("ROS_", "RMW_", "BRIDGEOS_CLOUD_KEY"))}
        assert launched.get("ROS_DISCOVERY_SERVER") == address, (process.cmdline(), launched)
        assert env["ROS_DOMAIN_ID"] == str(DOMAIN)
        assert _first_on_path(env) == VENV_BIN

        # And it talks in the robot's cloud graph, under its namespace.
        listener = node(LISTENER, [f"{namespace}/chatter", "12"], address)
        assert await asyncio.to_thread(heard, listener) > 0
    finally:
        if listener is not None:
            stop(listener)
        await link.send(Event.COMPONENT_STOP, {"skill": SKILL, "component": "talker", "location": "cloud"})
        # The stop done before the tables are flushed: the worker's writes would deadlock with the flush.
        await eventually(lambda: _copy_stopped("r2-copy"), timeout=60, what="the cloud copy stopped")
        await link.close()


@pytest.mark.parametrize(
    ("ros2", "field"),
    [
        ({"domain_id": 999}, "domain_id"),
        ({"rmw": "cyclone; rm -rf /"}, "rmw"),
        ({"discovery_range": "EVERYWHERE"}, "discovery_range"),
        ({"static_peers": ["a b"]}, "static_peers"),
        ("not a graph", "ros2"),
        ({"domain_id": 45, "extra": 1}, "extra"),
    ],
)
async def test_an_invalid_ros2_block_is_refused_clearly_and_changes_nothing(stack, ros2, field):
    robot_id = f"r2-bad-{field.replace('_', '-')}"
    token, _ = await make_robot(robot_id)
    frame = {"event": "authentication_robot", "id": "a1", "data": {"robot": robot_id, "token": token, "ros2": ros2}}
    async with websockets.connect(stack.ws_url + "/ws/robot/") as ws:
        await ws.send(json.dumps(frame))
        answer = protocol.decode(await asyncio.wait_for(ws.recv(), 10))
        assert answer.event == Event.AUTHENTICATION_FAILURE
        # The field and the reason, e.g. "data.ros2.domain_id: Input should be less than or equal to 232".
        assert f"data.ros2.{field}" in answer.data["reason"] or (
            field == "ros2" and "data.ros2" in answer.data["reason"]
        )
        with pytest.raises(websockets.ConnectionClosed):
            await asyncio.wait_for(ws.recv(), 10)
    robot = await sync_to_async(Robot.objects.get)(id=robot_id)
    assert not robot.connected and robot.ros2 is None
    assert await cloud_row(robot_id) is None
    assert await servers_of(stack, robot_id) == []


# --------------------------------------------------------------------------- checks


def _first_on_path(env: dict[str, str]) -> str:
    return os.path.realpath(env["PATH"].split(os.pathsep)[0])


async def _no_servers(stack, *robot_ids: str) -> bool:
    return not [o for o in await observe_async(stack.runtime) if o.robot in robot_ids and o.kind == KIND_ROS2_DISCOVERY]


async def _is(value, expected) -> bool:
    return (await value) == expected


@sync_to_async
def _disconnected(*robot_ids: str) -> bool:
    return not Robot.objects.filter(id__in=robot_ids, connected=True).exists()


@sync_to_async
def _copy_stopped(robot_id: str) -> bool:
    instance = CloudInstance.objects.filter(component__skill__robot_id=robot_id).first()
    return instance is None or (instance.desired == "stopped" and instance.status in ("stopped", "failed"))


@sync_to_async
def _copy_running(robot_id: str) -> bool:
    instance = CloudInstance.objects.filter(component__skill__robot_id=robot_id).first()
    if instance is not None and instance.status == "failed":
        raise AssertionError(f"the cloud copy failed: {instance.message}")
    return instance is not None and instance.status == "running"
