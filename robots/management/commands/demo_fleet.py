"""Create (or refresh) a demo fleet and print its robots' new tokens and an API token as JSON."""

from __future__ import annotations

import copy
import json
from importlib import resources
from typing import Any

from django.contrib.auth import get_user_model
from django.core.management.base import BaseCommand, CommandError, CommandParser

from bridgeos_agent.skillconfig import parse_skill_config
from robots.models import Robot, default_robot_config
from robots.rotation import rotate_token
from robots.services import create_robot, issue_api_token
from skills.models import Skill, SkillTemplate
from skills.services import add_skill

SAMPLE = "demo_telemetry.json"
# What a demo robot has: its robot config declares it (Algorithm 1's capacity, which an agent takes
# from the cloud's config) and its simulating agent swings its link down to `bandwidth_min` and back.
# Room for every component of a demo robot's Skills at once (two people detections need 4.6 cores and
# 2.3 GiB), on a link that holds them even at its low point (140 Mbit/s), however its swing is timed
# against their starts: they start on the robot, then the Skill Managers' estimates and the demo's
# own moves send components to the cloud and back.
DEMO_ROBOT = {"cpu": 8.0, "ram": 8192.0, "bandwidth": 400.0, "bandwidth_min": 160.0}
# The thesis's use cases (§5.3): in the catalog always; on demo robots (one each, in turn) with --usecases.
USE_CASES = {
    "people_detection.json": ("Detects people in a depth camera's pointclouds (thesis §5.3).", ["vision", "ros"]),
    "navigation.json": ("Drives a simulated robot to goals with a cloud path planner (thesis §5.3).", ["nav", "ros"]),
    "mapping.json": ("Maps a room from a simulated robot's laser and odometry (thesis §5.3).", ["mapping", "ros"]),
}
# The same use cases as ROS 2 nodes (rclpy): in the catalog always; on demo robots with --usecases2.
USE_CASES_ROS2 = {
    "people_detection_ros2.json": ("People detection as ROS 2 nodes (rclpy, Jazzy).", ["vision", "ros2"]),
    "navigation_ros2.json": ("Autonomous navigation as ROS 2 nodes (rclpy, Jazzy).", ["nav", "ros2"]),
    "mapping_ros2.json": ("Autonomous mapping as ROS 2 nodes (rclpy, Jazzy).", ["mapping", "ros2"]),
}


def sample(name: str) -> dict[str, Any]:
    return json.loads(resources.files("bridgeos_agent").joinpath("samples", name).read_text())


def demo_robot_config(config: dict[str, Any] | None = None) -> dict[str, Any]:
    """Return a robot config (a new robot's default, or ``config``) declaring a demo robot's resources."""
    config = copy.deepcopy(config) if config is not None else default_robot_config()
    config["resources"] = {**config["resources"], **{k: v for k, v in DEMO_ROBOT.items() if k != "bandwidth_min"}}
    return config


def catalog(samples: dict[str, tuple[str, list[str]]]) -> list[dict[str, Any]]:
    """Put sample Skills in the catalog (refreshed, never duplicated); return their configs."""
    configs = []
    for name, (description, tags) in samples.items():
        config = sample(name)
        SkillTemplate.objects.update_or_create(
            name=config["skill"], defaults={"config": config, "description": description, "tags": tags}
        )
        configs.append(config)
    return configs


class Command(BaseCommand):
    help = "Make robots demo-1..demo-N (each with the demo Skill) owned by USER; print their tokens as JSON."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--count", type=int, default=3, help="How many demo robots (default 3).")
        parser.add_argument("--owner", required=True, help="Username owning the demo robots.")
        parser.add_argument(
            "--usecases", action="store_true", help="Also give each robot a use-case Skill (needs ROS)."
        )
        parser.add_argument(
            "--usecases2", action="store_true", help="Also give each robot a ROS 2 use-case Skill (needs rclpy)."
        )

    def handle(self, *args: Any, **options: Any) -> None:
        if not 0 <= options["count"] <= 500:
            raise CommandError("--count must be between 0 and 500.")
        owner = get_user_model().objects.filter(username=options["owner"]).first()
        if owner is None:
            raise CommandError(f"No user named {options['owner']!r}.")
        config = sample(SAMPLE)
        use_cases = catalog(USE_CASES)
        use_cases_ros2 = catalog(USE_CASES_ROS2)
        robots = []
        for n in range(1, options["count"] + 1):
            robot_id = f"demo-{n}"
            robot = Robot.objects.filter(id=robot_id).first()
            if robot is None:
                robot, token = create_robot(robot_id, owner, name=f"Demo robot {n}", config=demo_robot_config())
            else:
                # Tokens are stored hashed: a restarted demo gets fresh ones.
                token = rotate_token(robot)
                if robot.config != demo_robot_config(robot.config):
                    robot.config = demo_robot_config(robot.config)
                    robot.save(update_fields=["config"])
            skills = [config] + ([use_cases[(n - 1) % len(use_cases)]] if options["usecases"] else [])
            skills += [use_cases_ros2[(n - 1) % len(use_cases_ros2)]] if options["usecases2"] else []
            for skill in skills:
                existing = Skill.objects.filter(robot=robot, skill_id=skill["skill_id"]).first()
                if existing is None:
                    add_skill(robot, skill)
                elif existing.config != parse_skill_config(skill).model_dump(mode="json"):
                    # A demo kept from an older run gets the Skill as it is now (e.g. its cloud images).
                    existing.config = skill
                    existing.save(update_fields=["config", "updated_at"])
            ids = [skill["skill_id"] for skill in skills]
            robots.append(
                {"id": robot_id, "token": token, "skill": config["skill_id"], "skills": ids, "simulate": DEMO_ROBOT}
            )
        self.stdout.write(json.dumps({"robots": robots, "api_token": issue_api_token(owner)[0]}))
