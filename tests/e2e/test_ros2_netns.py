"""ROS 2 end to end across a link without multicast: a robot in a network namespace, its listener moved
robot -> cloud -> robot through the REST API while it counts every message of a robot talker.

The cloud (daphne, a Celery worker, the process runtime) runs on this machine's side of a veth
pair with multicast switched off at both ends; the agent and its ROS 2 graph run in the robot's
namespace. The listener's cloud copy is a client of the robot's discovery server only, so what it
hears came through the router's cloud graph and over the link, by unicast.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

import pytest

from benchmarks.chaos.rig import Agent, Cloud, RobotLink, instances, kill_instances, tail, wait_until
from bridgeos_agent.ros2graph import rclpy_missing
from tests.net.netns import run

pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="puts the robot in a network namespace: needs root (ip netns)"),
    pytest.mark.skipif(rclpy_missing() is not None, reason="rclpy is not installed"),
    pytest.mark.timeout(240),
]

ROBOT = "ros2-netns"
SKILL = "ros2-relay"
NODES = str(Path(__file__).resolve().parents[1] / "agent" / "ros2nodes.py")
# UDP only: on one machine Fast DDS would otherwise carry data through shared memory, around the link.
DDS = {"FASTDDS_BUILTIN_TRANSPORTS": "UDPv4"}
RATE = 100


@pytest.fixture(autouse=True)
def own_stores(monkeypatch: pytest.MonkeyPatch) -> None:
    """Give the test's cloud a database beside the test database, the test's Redis and a ROS 2 graph of its own."""
    monkeypatch.setenv("BRIDGEOS_CHAOS_DATABASE_URL", os.environ["DATABASE_URL"] + "_ros2netns")
    monkeypatch.setenv("BRIDGEOS_CHAOS_REDIS_URL", os.environ["REDIS_URL"])
    for name, value in {
        **DDS,
        "ROS_DOMAIN_ID": "57",
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
    }.items():
        monkeypatch.setenv(name, value)
    monkeypatch.delenv("ROS_DISCOVERY_SERVER", raising=False)


def skill() -> dict:
    def node(*args: str) -> dict:
        return {"command": [sys.executable, NODES, *args], "env": DDS}

    return {
        "skill": "ROS 2 relay",
        "skill_id": SKILL,
        "components": {
            "talker": {
                "name": "Talker",
                "location": "robot",
                "ros": 2,
                "resources": {"cpu": 0.05, "ram": 64},
                "robot": node("talker", "--rate", str(RATE), "--tag", "r", "--linger", "0"),
            },
            "listener": {
                "name": "Listener",
                "location": "either",
                "ros": 2,
                "resources": {"cpu": 0.05, "ram": 64},
                "robot": node("listener"),
                "cloud": node("listener"),
            },
        },
        "router": {
            "topics": [
                {"name": "chatter", "type": "std_msgs/msg/String", "publisher": "talker", "subscribers": ["listener"]}
            ]
        },
    }


def heard(*roots: Path) -> list[int]:
    """Return every sequence number the listener's instances printed, robot's and cloud's, in file order."""
    seqs: list[int] = []
    for root in roots:
        for log in sorted(root.rglob(f"logs/{SKILL}/listener.log*"), reverse=True):
            for line in log.read_text(errors="replace").splitlines():
                parts = line.split()
                if len(parts) == 3 and parts[0] == "r" and parts[1].isdigit():
                    seqs.append(int(parts[1]))
    return seqs


def test_a_ros2_listener_moved_robot_cloud_robot_over_a_link_without_multicast_misses_nothing() -> None:
    link = RobotLink()
    for namespace, device in ((None, link.outside), (link.namespace, link.inside)):
        prefix = ["ip", "netns", "exec", namespace] if namespace else []
        run(*prefix, "ip", "link", "set", "dev", device, "multicast", "off")
    cloud = Cloud("ros2netns", host=link.cloud_address, celery=True)
    cloud.env["BRIDGEOS_CLOUD_HOST"] = link.cloud_address
    agent: Agent | None = None
    kill_instances(ROBOT, SKILL)
    try:
        cloud.start()
        token, api_token = cloud.add_robot(ROBOT, config={"offloading": "manual"}, skills=[skill()])
        cloud.wait_celery()
        agent = Agent(
            ROBOT,
            token,
            cloud.server.ws_url,
            cloud.dir / "agent",
            cloud.dir / "agent.log",
            namespace=link.namespace,
            options=["--ros2", "on"],
        )
        wait_until(lambda: (agent.try_scrape() or {}).get("bridgeos_agent_link_up") == 1, "the agent connected", 60)
        server = cloud.sql("SELECT ros2->>'cloud_discovery_server' FROM robots_robot WHERE id = %s", [ROBOT])[0][0]
        assert server.startswith(f"{link.cloud_address}:"), server
        answer = cloud.api(api_token, "POST", f"/api/robot/{ROBOT}/skill/{SKILL}/start", params={"wait": 30})
        assert answer.status_code == 200, answer.text
        roots = (cloud.dir / "agent", cloud.dir / "cloud")
        wait_until(lambda: len(heard(*roots)) >= RATE, "the robot listener hearing the talker", 60)

        migrate = f"/api/robot/{ROBOT}/skill/{SKILL}/component/listener/migrate"
        for where, root in (("cloud", roots[1]), ("robot", roots[0])):
            before = len(heard(root))
            answer = cloud.api(api_token, "POST", migrate, params={"wait": 60})
            assert answer.status_code == 200 and answer.json().get("accepted"), answer.text
            wait_until(
                lambda w=where: instances(ROBOT, SKILL)[("listener", w)] == 1, f"the listener on the {where}", 60
            )
            # Two seconds of the talker heard by the new instance itself (the switch comes once it is ready).
            wait_until(lambda r=root, b=before: len(heard(r)) >= b + 2 * RATE, f"messages heard in the {where}", 60)
        time.sleep(1.0)
        answer = cloud.api(api_token, "POST", f"/api/robot/{ROBOT}/skill/{SKILL}/stop", params={"wait": 30})
        time.sleep(1.0)
        seqs = heard(*roots)
        cloud_seqs = heard(roots[1])
        assert len(cloud_seqs) >= 2 * RATE, f"the cloud copy heard {len(cloud_seqs)} messages through the link"
        assert len(seqs) == len(set(seqs)), f"{len(seqs) - len(set(seqs))} messages heard twice"
        first, last = min(seqs), max(seqs)
        missing = sorted(set(range(first, last + 1)) - set(seqs))
        assert not missing, f"{len(missing)} of {last - first + 1} messages lost, e.g. {missing[:10]}"
    except BaseException:
        if agent is not None:
            print(tail(cloud.dir / "agent.log", 4000))
        print(tail(cloud.dir / "worker.log", 2000))
        raise
    finally:
        if agent is not None:
            agent.stop()
        cloud.stop()
        kill_instances(ROBOT, SKILL)
        link.close()
