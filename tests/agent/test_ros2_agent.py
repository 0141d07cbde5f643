"""The agent's ROS 2 door: the --ros2 option, the graph it reads from its env and what ROS 2 components get."""

from __future__ import annotations

from pathlib import Path

import pytest

from bridgeos_agent.cli import EXIT_USAGE, main
from bridgeos_agent.controller import AgentSettings, RobotController, SkillRecord
from bridgeos_agent.ros2graph import Ros2Graph
from bridgeos_agent.skillconfig import parse_skill_config

ROBOT_ARGS = ["run", "--master", "ws://127.0.0.1:9", "--robot", "r2-door", "--token", "t" * 20]


def mixed_skill() -> SkillRecord:
    """Return a Skill with a ROS 1 node, a ROS 2 node and a component that is no ROS node."""
    components = {
        name: {"name": name, "location": "robot", "ros": ros, "robot": {"command": ["sleep", "60"]}}
        for name, ros in (("legacy", True), ("modern", 2), ("plain", False))
    }
    return SkillRecord(config=parse_skill_config({"skill": "Mixed", "skill_id": "mixed", "components": components}))


@pytest.mark.parametrize(
    ("env", "args", "says"),
    [
        ({"BRIDGEOS_ROS2": "maybe"}, [], "must be auto, on or off"),
        ({"ROS_DOMAIN_ID": "300"}, ["--ros2", "on"], "ROS_DOMAIN_ID must be 0..232"),
        ({"ROS_DOMAIN_ID": "seven"}, ["--ros2", "on"], "not usable"),
        ({"ROS_AUTOMATIC_DISCOVERY_RANGE": "GALAXY"}, [], "discovery range must be one of"),
    ],
)
def test_a_bad_ros2_setting_is_refused_before_anything_starts(
    env: dict[str, str], args: list[str], says: str, monkeypatch: pytest.MonkeyPatch, capsys, tmp_path: Path
) -> None:
    for name, value in env.items():
        monkeypatch.setenv(name, value)
    data_dir = tmp_path / "data"
    assert main([*ROBOT_ARGS, "--data-dir", str(data_dir), *args]) == EXIT_USAGE
    assert says in capsys.readouterr().err
    assert not data_dir.exists()  # refused at the door: no state written


def test_the_graph_is_read_from_the_agents_env() -> None:
    graph = Ros2Graph.from_env(
        {"ROS_DOMAIN_ID": "7", "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "ROS_STATIC_PEERS": "10.0.0.2;robot-b"}
    )
    assert graph == Ros2Graph(domain_id=7, discovery_range="SUBNET", static_peers=("10.0.0.2", "robot-b"))
    assert graph.env() == {
        "ROS_DOMAIN_ID": "7",
        "RMW_IMPLEMENTATION": "rmw_fastrtps_cpp",
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET",
        "ROS_STATIC_PEERS": "10.0.0.2;robot-b",
    }
    # A discovery server replaces multicast discovery altogether.
    assert Ros2Graph(discovery_server="10.8.0.1:11811").env()["ROS_DISCOVERY_SERVER"] == "10.8.0.1:11811"


def test_each_component_gets_the_env_and_arguments_of_the_ros_it_speaks(tmp_path: Path) -> None:
    controller = RobotController(
        AgentSettings(master="ws://127.0.0.1:9", robot="r2-env", token="t" * 20, data_dir=tmp_path, simulate=True)
    )
    controller.ros_master = "http://127.0.0.1:11311"
    controller.ros2_graph = Ros2Graph(domain_id=9)
    record = mixed_skill()

    legacy = controller.component_spec(record, "legacy")
    assert legacy.env["ROS_NAMESPACE"] == "/bridgeos/mixed/legacy/robot"
    assert "ROS_DOMAIN_ID" not in legacy.env and legacy.launch.command == ["sleep", "60"]

    modern = controller.component_spec(record, "modern")
    namespace = "/bridgeos/mixed/modern/robot"
    assert modern.ros and modern.env["ROS_NAMESPACE"] == namespace
    assert modern.env["ROS_DOMAIN_ID"] == "9" and modern.env["RMW_IMPLEMENTATION"] == "rmw_fastrtps_cpp"
    assert modern.env["BRIDGEOS_ROS_ARGS"] == f"--ros-args -r __ns:={namespace}"
    assert modern.launch.command == ["sleep", "60", "--ros-args", "-r", f"__ns:={namespace}"]
    # The Skill's own config is not changed by the arguments given to one launch.
    assert record.config.components["modern"].robot.command == ["sleep", "60"]

    plain = controller.component_spec(record, "plain")
    assert not plain.ros and "ROS_NAMESPACE" not in plain.env and "BRIDGEOS_ROS_ARGS" not in plain.env


def test_simulated_robots_route_ros2_only_when_asked(tmp_path: Path) -> None:
    def graph(**kw: object) -> Ros2Graph | None:
        settings = AgentSettings(master="ws://127.0.0.1:9", robot="r2-sim", token="t" * 20, data_dir=tmp_path, **kw)
        return RobotController(settings)._detect_ros2()

    assert graph(simulate=True) is None
    assert graph(simulate=True, ros2="off") is None
    assert graph(simulate=True, ros2="on") == Ros2Graph.from_env()
    assert graph(ros2="auto") == Ros2Graph.from_env()  # rclpy is installed by make install
