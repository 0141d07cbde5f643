"""The use-case Skill configs: valid, placed as thesis Table 5.1 allows, runnable, in the catalog."""

from __future__ import annotations

import importlib
import io
import json

import pytest
from django.contrib.auth import get_user_model
from django.core.management import call_command

from bridgeos_agent.skillconfig import load_sample_skill_config
from bridgeos_agent.usecases import NODES
from robots.models import Robot
from skills.models import Skill, SkillTemplate

# Thesis Table 5.1 (plus the simulated robot, which stands in for the robot's own drivers).
TABLE_5_1 = {
    "people_detection": {"pointcloud": "robot", "sampler": "either", "detector": "either"},
    "navigation": {"planner": "cloud", "map-server": "either", "mover": "either", "sim": "robot"},
    "mapping": {"controller": "either", "mapping": "either", "odometry": "either", "sim": "robot"},
}


@pytest.mark.parametrize("sample", sorted(TABLE_5_1))
def test_each_use_case_is_placed_as_table_5_1_allows_and_its_commands_parse(sample: str) -> None:
    config = load_sample_skill_config(sample)
    assert {cid: c.location for cid, c in config.components.items()} == TABLE_5_1[sample]
    for cid, component in config.components.items():
        for where in ("robot", "cloud"):
            spec = component.launch_spec(where)
            if spec is None:
                continue
            assert spec.image == "bridgeos/ros:noetic", cid
            program, node, *args = spec.command
            assert program == "bridgeos-usecase" and node in NODES, spec.command
            # The node's own argument parser accepts the config's arguments (no rospy needed for that).
            importlib.import_module(f"bridgeos_agent.usecases.{NODES[node]}").parse_args(args)
    routed = {c for topic in config.router.topics for c in (topic.publisher, *topic.subscribers)}
    assert routed == set(config.components), "every component is wired through the router's topics"


@pytest.mark.parametrize("sample", sorted(TABLE_5_1))
def test_each_ros2_use_case_is_its_ros1_twin_on_ros2_nodes(sample: str) -> None:
    """Same components, places, resources, arguments and topics; ROS 2 nodes, types, image and script.

    Memory alone may differ: a ROS 2 node (rclpy and its DDS participant) needs more than its rospy twin.
    """
    ros1, ros2 = load_sample_skill_config(sample), load_sample_skill_config(f"{sample}_ros2")
    assert ros2.skill_id == f"{ros1.skill_id}-ros2" and ros2.skill != ros1.skill
    assert set(ros2.components) == set(ros1.components)
    for cid, component in ros2.components.items():
        twin = ros1.components[cid]
        assert component.ros_version == 2 and twin.ros_version == 1
        assert (component.location, component.resources.model_copy(update={"ram": twin.resources.ram})) == (
            twin.location,
            twin.resources,
        )
        assert component.resources.ram >= twin.resources.ram, cid
        for where in ("robot", "cloud"):
            spec, twin_spec = component.launch_spec(where), twin.launch_spec(where)
            assert (spec is None) == (twin_spec is None), (cid, where)
            if spec is None or twin_spec is None:
                continue
            assert spec.image == "bridgeos/ros2:jazzy", cid
            program, node, *args = spec.command
            assert program == "bridgeos-usecase2" and [node, *args] == twin_spec.command[1:], spec.command
            importlib.import_module(f"bridgeos_agent.usecases.{NODES[node]}").parse_args(args)
    for topic, twin in zip(ros2.router.topics, ros1.router.topics, strict=True):
        package, kind, name = topic.type.split("/")
        assert kind == "msg" and twin.type == f"{package}/{name}", topic.type
        assert (topic.name, topic.publisher, topic.subscribers) == (twin.name, twin.publisher, twin.subscribers)


def test_a_node_refuses_bad_arguments_with_a_clear_message(capsys: pytest.CaptureFixture[str]) -> None:
    sim = importlib.import_module("bridgeos_agent.usecases.sim")
    with pytest.raises(SystemExit):
        sim.parse_args(["--world", "mars"])
    assert "unknown world 'mars' (known: office, room)" in capsys.readouterr().err


@pytest.mark.django_db
def test_the_demo_fleet_puts_the_use_cases_in_the_catalog_and_on_its_robots() -> None:
    get_user_model().objects.create_user("operator")

    def demo(*extra: str) -> dict:
        out = io.StringIO()
        call_command("demo_fleet", "--count", "3", "--owner", "operator", *extra, stdout=out)
        return json.loads(out.getvalue())

    plain = demo()
    assert all(robot["skills"] == ["demo-telemetry"] for robot in plain["robots"])
    names = set(SkillTemplate.objects.values_list("name", flat=True))
    assert {"People detection", "Autonomous navigation", "Autonomous mapping"} <= names

    fleet = demo("--usecases")  # twice: the catalog is refreshed, never duplicated
    assert [robot["skills"][1] for robot in fleet["robots"]] == ["people-detection", "navigation", "mapping"]
    assert SkillTemplate.objects.filter(name="Autonomous mapping").count() == 1
    assert Skill.objects.get(robot_id="demo-2", skill_id="navigation").components.count() == 4
    ros2_names = {"People detection (ROS 2)", "Autonomous navigation (ROS 2)", "Autonomous mapping (ROS 2)"}
    assert ros2_names <= set(SkillTemplate.objects.values_list("name", flat=True))

    both = demo("--usecases", "--usecases2")
    assert [robot["skills"][1:] for robot in both["robots"]] == [
        ["people-detection", "people-detection-ros2"],
        ["navigation", "navigation-ros2"],
        ["mapping", "mapping-ros2"],
    ]
    assert SkillTemplate.objects.filter(name="Autonomous mapping (ROS 2)").count() == 1
    skill = Skill.objects.get(robot_id="demo-3", skill_id="mapping-ros2")
    assert skill.config["components"]["mapping"]["ros"] == 2

    # The capacity its agent simulates is the capacity its robot config declares: an agent takes
    # the config's, so a demo robot declared at the default 100 Mbit/s could not hold its Skills.
    for robot in both["robots"]:
        declared = Robot.objects.get(id=robot["id"]).config["resources"]
        simulate = robot["simulate"]
        assert (declared["cpu"], declared["ram"], declared["bandwidth"]) == (
            simulate["cpu"],
            simulate["ram"],
            simulate["bandwidth"],
        )
    # At its link's low point demo-1 holds both its people detections wholly on the robot.
    detections = [load_sample_skill_config(name) for name in ("people_detection", "people_detection_ros2")]
    needs = sum(c.resources.bandwidth for skill in detections for c in skill.components.values())
    assert both["robots"][0]["simulate"]["bandwidth_min"] >= needs
