"""Create (or refresh) a demo fleet and print its robots' new tokens and an API token as JSON."""

from __future__ import annotations

import json
from importlib import resources
from typing import Any

from django.contrib.auth import get_user_model
from django.core.management.base import BaseCommand, CommandError, CommandParser

from bridgeos_agent.skillconfig import parse_skill_config
from robots.models import Robot
from robots.services import create_robot, issue_api_token, rotate_token
from skills.models import Skill
from skills.services import add_skill

SAMPLE = "demo_telemetry.json"


class Command(BaseCommand):
    help = "Make robots demo-1..demo-N (each with the demo Skill) owned by USER; print their tokens as JSON."

    def add_arguments(self, parser: CommandParser) -> None:
        parser.add_argument("--count", type=int, default=3, help="How many demo robots (default 3).")
        parser.add_argument("--owner", required=True, help="Username owning the demo robots.")

    def handle(self, *args: Any, **options: Any) -> None:
        if not 0 <= options["count"] <= 500:
            raise CommandError("--count must be between 0 and 500.")
        owner = get_user_model().objects.filter(username=options["owner"]).first()
        if owner is None:
            raise CommandError(f"No user named {options['owner']!r}.")
        config = json.loads(resources.files("bridgeos_agent").joinpath("samples", SAMPLE).read_text())
        robots = []
        for n in range(1, options["count"] + 1):
            robot_id = f"demo-{n}"
            robot = Robot.objects.filter(id=robot_id).first()
            if robot is None:
                robot, token = create_robot(robot_id, owner, name=f"Demo robot {n}")
            else:
                # Tokens are stored hashed: a restarted demo gets fresh ones.
                token = rotate_token(robot)
            skill = Skill.objects.filter(robot=robot, skill_id=config["skill_id"]).first()
            if skill is None:
                add_skill(robot, config)
            elif skill.config != parse_skill_config(config).model_dump(mode="json"):
                # A demo kept from an older run gets the sample as it is now (e.g. its cloud images).
                skill.config = config
                skill.save(update_fields=["config", "updated_at"])
            robots.append({"id": robot_id, "token": token, "skill": config["skill_id"]})
        self.stdout.write(json.dumps({"robots": robots, "api_token": issue_api_token(owner)[0]}))
