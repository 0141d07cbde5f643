"""Cloud copies on Docker Swarm, driven by a real Celery worker, for a real agent over real sockets.

A robot (the agent's RobotController, process runtime) asks its cloud for copies; the cloud's
worker runs them as Swarm services from the local ROS image. Nothing here is mocked: the
worker is killed with SIGKILL, containers with `docker kill`, and ROS nodes on both sides
talk through the robot's own ROS master, which the cloud runs as a Swarm service too.
"""

from __future__ import annotations

import asyncio
import itertools
import subprocess
import time
import urllib.request

import httpx
import pytest
from asgiref.sync import sync_to_async

import docker
from bridgeos_agent.controller import RobotController
from bridgeos_agent.skillconfig import parse_skill_config
from monitoring.models import Event, Metric
from skills.cloud.runtime import KIND_ROS_MASTER, object_name
from skills.models import CloudInstance, Component, RobotCloud
from tests.agent.conftest import agent_settings, configured, make_robot
from tests.conftest import eventually
from tests.e2e.conftest import host_ros_env

from .conftest import make_stack, observe_async

pytestmark = [
    pytest.mark.django_db(transaction=True),
    pytest.mark.docker,
    pytest.mark.ros,
    pytest.mark.timeout(240),
    pytest.mark.usefixtures("robots_disconnect_before_flush"),
]

SKILL = "cloudy"
IMAGE = "bridgeos/ros:noetic"
HOST_PYTHON = "/usr/bin/python3"

# In the cloud: answers every ping from the robot on its own (namespaced) "pong" topic.
ECHO = """
import rospy
from std_msgs.msg import String
rospy.init_node("echo")
pong = rospy.Publisher("pong", String, queue_size=10)
rospy.Subscriber("/wtcloud_ping", String, lambda m: pong.publish(String(data="pong:" + m.data)))
rospy.spin()
"""

# On the robot: pings the cloud node and prints each answer it gets back.
CALLER = """
import rospy
from std_msgs.msg import String
rospy.init_node("caller")
rospy.Subscriber("/bridgeos/cloudy/echo/cloud/pong", String, lambda m: print("got", m.data, flush=True))
ping = rospy.Publisher("/wtcloud_ping", String, queue_size=10)
n = 0
rate = rospy.Rate(5)
while not rospy.is_shutdown():
    ping.publish(String(data="ping %d" % n))
    n += 1
    rate.sleep()
"""

TICKER = "echo started; i=0; while true; do i=$((i+1)); echo tick $i; sleep 1; done"


@pytest.fixture(scope="module")
def stack(django_db_setup, django_db_blocker, tmp_path_factory):
    yield from make_stack("swarm", tmp_path_factory.mktemp("swarm"))


def skill(**components: dict) -> dict:
    return parse_skill_config({"skill": "Cloudy", "skill_id": SKILL, "components": components}).model_dump(mode="json")


def web_component() -> dict:
    return {
        "name": "Web",
        "location": "cloud",
        "ros": False,
        "resources": {"cpu": 0.2, "ram": 64},
        "cloud": {"image": IMAGE, "command": ["python3", "-m", "http.server", "8080"], "ports": [8080]},
    }


def ticker_component() -> dict:
    return {
        "name": "Ticker",
        "location": "cloud",
        "ros": False,
        "cloud": {"image": IMAGE, "command": ["sh", "-c", TICKER]},
    }


@sync_to_async
def instance_of(robot_id: str, component: str) -> CloudInstance | None:
    return CloudInstance.objects.filter(component__skill__robot_id=robot_id, component__component_id=component).first()


@sync_to_async
def component_row(robot_id: str, component: str) -> Component:
    return Component.objects.get(skill__robot_id=robot_id, component_id=component)


@sync_to_async
def events_of(robot_id: str, kind: str) -> list[Event]:
    return list(Event.objects.filter(robot_id=robot_id, kind=kind).order_by("ts"))


async def running_instance(robot_id: str, component: str) -> CloudInstance | None:
    instance = await instance_of(robot_id, component)
    return instance if instance is not None and instance.status == "running" else None


def service_tasks(client: docker.DockerClient, name: str) -> list[dict]:
    try:
        return client.services.get(name).tasks()
    except docker.errors.NotFound:
        return []


async def test_a_cloud_component_runs_as_a_swarm_service_with_its_env_and_network(stack, tmp_path):
    token, _ = await make_robot("swarm-1", skill=skill(web=web_component()))
    settings = agent_settings(stack.server, "swarm-1", token, tmp_path / "agent", detect_ros_master=False)
    controller = RobotController(settings, plugins={})
    client = docker.from_env()
    async with configured(controller):
        # No ROS master on this robot: the cloud runs one of its own for it and says where.
        assert controller.ros_master is not None and controller.ros_master.startswith("http://127.0.0.1:")
        record = await controller.start_skill(parse_skill_config(skill(web=web_component())))
        assert record.locations == {"web": "cloud"}
        instance = await eventually(lambda: running_instance("swarm-1", "web"), timeout=90, what="web running")

        service = client.services.get(object_name("swarm-1", SKILL, "web"))
        spec = service.attrs["Spec"]
        assert spec["EndpointSpec"]["Mode"] == "dnsrr"
        assert spec["EndpointSpec"]["Ports"] == [{"Protocol": "tcp", "TargetPort": 8080, "PublishMode": "host"}]
        container = spec["TaskTemplate"]["ContainerSpec"]
        assert container["Init"] is True
        env = dict(item.split("=", 1) for item in container["Env"])
        assert env["BRIDGEOS_ROBOT"] == "swarm-1" and env["BRIDGEOS_SKILL"] == SKILL
        assert env["BRIDGEOS_COMPONENT"] == "web" and env["BRIDGEOS_LOCATION"] == "cloud"
        assert env["ROS_MASTER_URI"] == controller.ros_master
        limits = spec["TaskTemplate"]["Resources"]["Limits"]
        assert limits == {"NanoCPUs": 200_000_000, "MemoryBytes": 64 * 1024 * 1024}
        assert spec["Labels"]["io.bridgeos.cloud"] == stack.cloud_id
        # On the robot's own attachable overlay network.
        network = client.networks.get(object_name("swarm-1", kind="network"))
        assert network.attrs["Driver"] == "overlay" and network.attrs["Attachable"] is True
        assert [n["Target"] for n in spec["TaskTemplate"]["Networks"]] == [network.id]
        # ... whose subnet is the robot's cloud subnet (IPAM), the one its VPN routes to.
        assert [c["Subnet"] for c in network.attrs["IPAM"]["Config"]] == [await _cloud_subnet("swarm-1")]

        # The robot heard where to reach it: the cloud host and the port Swarm published in host mode.
        info = await eventually(lambda: record.cloud_containers.get("web"), what="component_information")
        assert info["runtime"] == "swarm" and info["address"] == "127.0.0.1"
        published = info["ports"]["8080"]
        assert info == instance.container
        # The server in the copy may take a moment to listen once its container runs.
        body = await eventually(lambda: _fetch(f"http://127.0.0.1:{published}/"), what="the copy's HTTP server")
        assert b"Directory listing" in body
        row = await component_row("swarm-1", "web")
        assert (row.status, row.active_location, row.container["cloud"]) == ("running", "cloud", info)

        await controller.stop_skill(SKILL)
        await eventually(lambda: _no_service(client, "swarm-1", "web"), timeout=60, what="service removed")
        await eventually(lambda: _status_is("swarm-1", "web", "stopped"), what="the copy recorded stopped")


@sync_to_async
def _cloud_subnet(robot_id: str) -> str:
    from network.ipam import subnets
    from robots.models import Robot

    return subnets(Robot.objects.get(id=robot_id))[1]


async def _fetch(url: str) -> bytes | None:
    try:
        return await asyncio.to_thread(lambda: urllib.request.urlopen(url, timeout=5).read())
    except OSError:
        return None


async def _status_is(robot_id: str, component: str, status: str) -> bool:
    instance = await instance_of(robot_id, component)
    return instance is not None and instance.status == status


async def _no_service(client: docker.DockerClient, robot: str, component: str) -> bool:
    try:
        await asyncio.to_thread(client.services.get, object_name(robot, SKILL, component))
    except docker.errors.NotFound:
        return True
    return False


async def test_a_robot_without_a_ros_master_gets_one_and_its_nodes_talk_to_cloud_nodes(stack, tmp_path):
    components = {
        "echo": {"name": "Echo", "location": "cloud", "cloud": {"image": IMAGE, "command": ["python3", "-c", ECHO]}},
        "caller": {
            "name": "Caller",
            "location": "robot",
            "robot": {"command": [HOST_PYTHON, "-c", CALLER], "env": {"ROS_IP": "127.0.0.1"}},
        },
    }
    token, _ = await make_robot("swarm-2", skill=skill(**components))
    settings = agent_settings(stack.server, "swarm-2", token, tmp_path / "agent", detect_ros_master=False)
    controller = RobotController(settings, plugins={})
    async with configured(controller):
        master = controller.ros_master
        port = int(master.rsplit(":", 1)[1])
        low, high = (int(p) for p in stack.env["BRIDGEOS_CLOUD_ROS_MASTER_PORTS"].split("-"))
        assert low <= port <= high
        await eventually(
            lambda: _master_running(stack.runtime, "swarm-2"), timeout=90, what="the robot's ROS master service"
        )
        cloud = await eventually(lambda: _master_recorded("swarm-2"), what="the master recorded running")
        assert cloud.ros_master_port == port

        await controller.start_skill(parse_skill_config(skill(**components)))
        await eventually(lambda: running_instance("swarm-2", "echo"), timeout=90, what="echo running in the cloud")
        # A ping from the robot's node reached the cloud node, whose answer came back.
        answered = await eventually(lambda: _caller_got_pong(controller), timeout=90, what="a pong from the cloud node")
        assert answered.startswith("got pong:ping ")
        service = docker.from_env().services.get(object_name("swarm-2", SKILL, "echo"))
        env = dict(item.split("=", 1) for item in service.attrs["Spec"]["TaskTemplate"]["ContainerSpec"]["Env"])
        assert env["ROS_NAMESPACE"] == f"/bridgeos/{SKILL}/echo/cloud"
        assert env["ROS_MASTER_URI"] == master and env["ROS_IP"] == "127.0.0.1"
        await controller.stop_skill(SKILL)


@sync_to_async
def _master_recorded(robot_id: str) -> RobotCloud | None:
    return RobotCloud.objects.filter(robot_id=robot_id, ros_master_status="running").first()


async def _master_running(runtime: str, robot_id: str) -> bool:
    return any(
        o.kind == KIND_ROS_MASTER and o.robot == robot_id and o.status == "running"
        for o in await observe_async(runtime)
    )


async def _caller_got_pong(controller: RobotController) -> str | None:
    lines = await controller.runtime.logs(SKILL, "caller", 50)
    return next((line for line in lines if line.startswith("got pong:")), None)


async def test_the_reconciler_restarts_a_killed_cloud_container_and_logs_why(stack, tmp_path):
    token, _ = await make_robot("swarm-3", skill=skill(ticker=ticker_component()))
    controller = RobotController(agent_settings(stack.server, "swarm-3", token, tmp_path / "agent"), plugins={})
    client = docker.from_env()
    async with configured(controller):
        record = await controller.start_skill(parse_skill_config(skill(ticker=ticker_component())))
        first = await eventually(lambda: running_instance("swarm-3", "ticker"), timeout=90, what="ticker running")
        await eventually(lambda: record.cloud_containers.get("ticker"), what="the robot told where it runs")
        old_id = first.container["id"]
        await asyncio.to_thread(lambda: client.containers.get(old_id).kill())

        # The reconciler sees the dead copy, logs it with its last output and restarts it with backoff.
        async def restarted() -> CloudInstance | None:
            await asyncio.to_thread(stack.reconcile)
            instance = await instance_of("swarm-3", "ticker")
            return instance if instance.status == "running" and instance.container.get("id") != old_id else None

        again = await eventually(restarted, timeout=90, what="the copy restarted", interval=0.1)
        crashes = await events_of("swarm-3", "cloud_component_crashed")
        assert len(crashes) == 1 and crashes[0].level == "error"
        assert "started" in crashes[0].data["logs"] and crashes[0].data["exit_code"] == 137
        assert again.crashes and again.restarts == 1
        tasks = await asyncio.to_thread(service_tasks, client, object_name("swarm-3", SKILL, "ticker"))
        assert sum(t["Status"]["State"] == "running" for t in tasks) == 1
        # The robot heard of the crash and of the copy running again, at its new container.
        await eventually(
            lambda: record.cloud_containers["ticker"].get("id") == again.container["id"], what="new container told"
        )
        assert record.statuses["ticker"] == "running"

        # Each round measures the copy: its CPU and memory become metrics of the robot, labelled as the cloud's.
        async def measured() -> list[Metric]:
            await asyncio.to_thread(stack.reconcile)
            return await sync_to_async(list)(Metric.objects.filter(robot_id="swarm-3", component="ticker", name="ram"))

        ram = await eventually(measured, timeout=60, what="the copy's memory stored", interval=0.1)
        assert all(point.labels == {"location": "cloud"} and point.value > 0 for point in ram)
        await controller.stop_skill(SKILL)


async def test_a_worker_killed_mid_start_leaves_exactly_one_copy(stack, tmp_path):
    token, _ = await make_robot("swarm-4", skill=skill(ticker=ticker_component()))
    controller = RobotController(agent_settings(stack.server, "swarm-4", token, tmp_path / "agent"), plugins={})
    client = docker.from_env()
    name = object_name("swarm-4", SKILL, "ticker")
    try:
        async with configured(controller):
            await controller.start_skill(parse_skill_config(skill(ticker=ticker_component())))
            # Kill the worker (its whole process group) the moment the service exists: mid-task.
            await eventually(lambda: not _sync_no_service(client, name), timeout=60, what="the service created")
            stack.kill_worker()
            killed_before_recorded = (await instance_of("swarm-4", "ticker")).status != "running"
            stack.start_worker()

            async def settled() -> CloudInstance | None:
                await asyncio.to_thread(stack.reconcile)
                return await running_instance("swarm-4", "ticker")

            try:
                instance = await eventually(settled, timeout=90, what="the copy adopted", interval=0.1)
            except AssertionError:
                row = await instance_of("swarm-4", "ticker")
                seen = [(o.component, o.status) for o in await observe_async("swarm") if o.robot == "swarm-4"]
                raise AssertionError(
                    f"not adopted: row {row.desired}/{row.status} {row.message!r}, engine {seen}\n{stack.worker_log()}"
                ) from None
            tasks = await asyncio.to_thread(service_tasks, client, name)
            running_tasks = [t for t in tasks if t["Status"]["State"] == "running"]
            assert len(running_tasks) == 1, tasks
            assert running_tasks[0]["Status"]["ContainerStatus"]["ContainerID"] == instance.container["id"]
            copies = [o for o in await observe_async("swarm") if o.robot == "swarm-4"]
            assert [(o.component, o.status) for o in copies] == [("ticker", "running")]
            # The redelivered start (visibility timeout) finds the same copy again: still exactly one.
            await asyncio.sleep(1)
            containers = await asyncio.to_thread(
                client.containers.list,
                filters={"label": [f"io.bridgeos.cloud={stack.cloud_id}", "io.bridgeos.robot=swarm-4"]},
            )
            assert len(containers) == 1
            print(f"worker killed {'before' if killed_before_recorded else 'after'} the start was recorded")
            await controller.stop_skill(SKILL)
    finally:
        if stack.worker is None:
            stack.start_worker()


def _sync_no_service(client: docker.DockerClient, name: str) -> bool:
    try:
        client.services.get(name)
    except docker.errors.NotFound:
        return True
    return False


def test_ids_stay_unique_and_short_for_swarm() -> None:
    long_robot = "r" * 64
    names = {object_name(long_robot, "s" * 64, f"c{n}") for n in range(50)}
    assert len(names) == 50 and all(len(name) <= 63 for name in names)
    assert object_name("a-b", "c", "d") != object_name("a", "b-c", "d")


# A talker that keeps its count in the Skill's volume: a new copy continues where the last one was.
# It publishes "<where it runs> <count>" on its relative "chatter" (in the namespace the Skill Router
# gives each instance), and waits for a subscriber (the router) before it starts.
TALKER = """
import os, rospy
from std_msgs.msg import String
state = os.path.join(os.environ["BRIDGEOS_VOLUMES"], "state")
os.makedirs(state, exist_ok=True)
try:
    seq = int(open(os.path.join(state, "seq")).read())
except (OSError, ValueError):
    seq = 0
rospy.init_node("talker", anonymous=True)
pub = rospy.Publisher("chatter", String, queue_size=100)
while pub.get_num_connections() == 0 and not rospy.is_shutdown():
    rospy.sleep(0.05)
rate = rospy.Rate(20)
where = os.environ["BRIDGEOS_LOCATION"]
while not rospy.is_shutdown():
    seq += 1
    pub.publish(String(data="%s %d" % (where, seq)))
    temp = os.path.join(state, ".bridgeos-sync-seq")
    with open(temp, "w") as out:
        out.write(str(seq))
    os.replace(temp, os.path.join(state, "seq"))
    rate.sleep()
"""

# Outside the Skill, on the name its peers use: prints "where count monotonic-time" per message.
LISTENER = """
import time, rospy
from std_msgs.msg import String
rospy.init_node("wtc_listener", anonymous=True)
rospy.Subscriber("/chatter", String, lambda m: print(m.data, time.monotonic(), flush=True))
rospy.spin()
"""


async def test_a_ros_talker_migrates_robot_to_cloud_to_robot_while_a_listener_counts(stack, tmp_path):
    from bridgeos_agent.router import skill_router_plugin

    talker = {
        "name": "Talker",
        "location": "either",
        "robot": {"command": [HOST_PYTHON, "-c", TALKER], "env": {"ROS_IP": "127.0.0.1"}},
        "cloud": {"image": IMAGE, "command": ["python3", "-c", TALKER]},
    }
    route = {"name": "chatter", "type": "std_msgs/String", "publisher": "talker"}
    config = {
        "skill": "Talk",
        "skill_id": SKILL,
        "volumes": ["state"],
        "router": {"topics": [route]},
        "components": {"talker": talker},
    }
    config = parse_skill_config(config).model_dump(mode="json")
    token, api_token = await make_robot("swarm-5", skill=config)
    settings = agent_settings(stack.server, "swarm-5", token, tmp_path / "agent", detect_ros_master=False)
    # The Skill Router, and no manager that might move the talker on its own.
    controller = RobotController(settings, plugins={"router": skill_router_plugin})
    heard = tmp_path / "heard.txt"
    listener = None
    headers = {"Authorization": f"Token {api_token}"}
    path = f"/api/robot/swarm-5/skill/{SKILL}/component/talker/migrate"
    try:
        async with configured(controller), httpx.AsyncClient(base_url=stack.url, headers=headers, timeout=90) as api:
            await eventually(lambda: _master_recorded("swarm-5"), timeout=60, what="the robot's ROS master")
            env = {**host_ros_env(), "ROS_MASTER_URI": controller.ros_master}
            listener = await asyncio.to_thread(_spawn, [HOST_PYTHON, "-c", LISTENER], env, heard)
            await controller.start_skill(parse_skill_config(config))
            await eventually(lambda: _heard(heard, "robot", 40), timeout=90, what="the talker on the robot")

            switches = []
            for target in ("cloud", "robot"):
                began = time.monotonic()
                answer = await api.post(path, json={"location": target}, params={"wait": 60})
                assert answer.status_code == 200 and answer.json()["accepted"], answer.text
                switches.append((began, time.monotonic()))
                # When the API answers, the move is done: the database says so and the old copy is gone.
                row = await component_row("swarm-5", "talker")
                assert (row.status, row.active_location) == ("running", target)
                assert _runs_on_robot(controller, "talker") == (target == "robot")
                await eventually(
                    lambda t=target, b=began: _heard(heard, t, 40, after=b), timeout=90, what=f"the talker, {target}"
                )
            await controller.stop_skill(SKILL)
    finally:
        if listener is not None:
            listener.terminate()
            listener.wait(15)

    messages = _messages(heard)
    # Heard from the robot, then the cloud, then the robot again: one copy at a time, never both.
    segments: list[tuple[str, list[int]]] = []
    for where, seq, _ in messages:
        if not segments or segments[-1][0] != where:
            segments.append((where, []))
        segments[-1][1].append(seq)
    assert [where for where, _ in segments] == ["robot", "cloud", "robot"], [(w, len(s)) for w, s in segments]
    # No message lost and none twice while a copy was the active one: each count follows the last by one.
    for _, seqs in segments:
        assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), seqs
    # Each new copy went on from the count its Skill volume carried across (robot → cloud → robot).
    # (Not from 1 again; heard from the switch on, so a little past the count the volume carried.)
    robot_last, cloud_first, back_first = segments[0][1][-1], segments[1][1][0], segments[2][1][0]
    assert 1 < cloud_first < robot_last + 20 and cloud_first < back_first
    # No silence beyond the switches: a new copy is switched to once it is ready.
    times = [t for _, _, t in messages]
    longest = max(after - before for before, after in itertools.pairwise(times))
    print(f"{len(messages)} messages, longest silence {longest:.3f} s")
    assert longest < 2.0


def _runs_on_robot(controller: RobotController, component: str) -> bool:
    return any(
        entry["skill"] == SKILL and entry["component"] == component
        for entry in controller.runtime.get_state().get("components", [])
    )


def _spawn(command: list[str], env: dict[str, str], out_path) -> subprocess.Popen:
    with out_path.open("w") as out:
        return subprocess.Popen(command, env=env, stdout=out, stderr=subprocess.STDOUT)


def _messages(path) -> list[tuple[str, int, float]]:
    found = []
    for line in path.read_text().splitlines():
        parts = line.split()
        if len(parts) == 3 and parts[0] in ("robot", "cloud") and parts[1].isdigit():
            found.append((parts[0], int(parts[1]), float(parts[2])))
    return found


async def _heard(path, where: str, count: int, after: float = 0.0) -> bool:
    messages = await asyncio.to_thread(_messages, path)
    return sum(1 for w, _, t in messages if w == where and t >= after) >= count
