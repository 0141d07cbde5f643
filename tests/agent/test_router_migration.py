"""Migrations through the Skill Router: the real agent, the real cloud, rospy components, a private rosmaster.

The cloud's worker runs the cloud copy (process runtime); the copy waits for a file before it
starts publishing, so the test decides when the cloud instance can become ready.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from bridgeos_agent.controller import RobotController
from bridgeos_agent.protocol import ProtocolError
from bridgeos_agent.skillconfig import parse_skill_config
from tests.agent.conftest import agent_settings, configured, make_robot
from tests.agent.roshelpers import HOST_PYTHON, NODES
from tests.conftest import eventually

pytestmark = [pytest.mark.ros, pytest.mark.django_db(transaction=True), pytest.mark.timeout(180)]

SKILL = "chat"


def chat_skill(home: Path) -> dict:
    """Return a Skill whose talker is a rospy node; its cloud copy publishes once `home/go` exists."""

    def launch(tag: str) -> dict:
        command = [HOST_PYTHON, NODES, "talker", "--tag", tag, "--rate", "100"]
        if tag == "cloud":
            wait = f"while [ ! -e {home / 'go'} ]; do sleep 0.1; done; exec "
            command = ["sh", "-c", wait + " ".join(command)]
        return {"command": command, "env": {"ROS_IP": "127.0.0.1", "ROS_HOME": str(home), "PYTHONWARNINGS": "ignore"}}

    config = {
        "skill": "Chat",
        "skill_id": SKILL,
        "components": {
            "talker": {
                "name": "Talker",
                "location": "either",
                "resources": {"cpu": 0.1, "ram": 32},
                "robot": launch("robot"),
                "cloud": launch("cloud"),
            }
        },
        "router": {"topics": [{"name": "chatter", "type": "std_msgs/String", "publisher": "talker"}]},
    }
    return parse_skill_config(config).model_dump(mode="json")


async def test_a_migration_switches_only_once_the_new_instance_is_ready(cloud, rosmaster, nodes, tmp_path, monkeypatch):
    monkeypatch.setenv("BRIDGEOS_ROUTER_READY_TIMEOUT", "3")
    token, _ = await make_robot("route-1", skill=chat_skill(tmp_path))
    controller = RobotController(agent_settings(cloud, "route-1", token, tmp_path / "agent", detect_ros_master=False))
    controller.local_ros_master = controller.ros_master = rosmaster
    async with configured(controller):
        record = await controller.start_skill(parse_skill_config(chat_skill(tmp_path)))
        router = record.supervisor.context["router"]
        assert router.active("talker") == "robot"
        nodes.run("listener", "listener", "--topic", "/chatter")
        # The robot copy got its namespace from the controller; the router relays it to /chatter.
        await eventually(lambda: len(nodes.messages("listener")) >= 10, 60, "the robot talker on /chatter")

        # The cloud copy runs but never gets ready: the migration gives up, the robot copy keeps
        # running and routed.
        with pytest.raises(ProtocolError, match="not ready on the cloud within 3 s; it keeps running on the robot"):
            await controller.migrate_component(record, "talker", "cloud")
        assert record.locations["talker"] == "robot" and router.active("talker") == "robot"
        heard = len(nodes.messages("listener"))
        await eventually(lambda: len(nodes.messages("listener")) >= heard + 10, 30, "the robot copy still heard")

        # Now the cloud copy publishes as soon as it starts: the switch happens once it is ready.
        (tmp_path / "go").touch()
        # (Its rospy start may take longer than 3 s on a loaded machine.)
        router.settings.ready_timeout = 60
        assert await controller.migrate_component(record, "talker", "cloud") == "cloud"
        assert router.active("talker") == "cloud" and record.locations["talker"] == "cloud"
        await eventually(lambda: not controller.runtime.get_state().get("components"), 30, "robot copy stopped")
        cut = len(nodes.messages("listener"))
        await eventually(lambda: len(nodes.messages("listener")) >= cut + 20, 30, "the cloud talker on /chatter")
        tags = [tag for tag, _ in nodes.messages("listener")]
        first_cloud = tags.index("cloud")
        assert set(tags[first_cloud:]) == {"cloud"} and set(tags[:first_cloud]) == {"robot"}
