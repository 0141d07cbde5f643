"""The rig's own command, run in child processes so the runner's process never sets Django up for them.

python -m benchmarks.chaos.rig robots --prefix P --count N   # (create_robots) print [[id, token], ...]
python -m benchmarks.chaos.rig robot < SPEC.json             # (Cloud.add_robot) one robot, its config, Skills
python -m benchmarks.chaos.rig api-token                     # (api_token) a key for the robots' owner
python -m benchmarks.chaos.rig fleet SPEC.json               # (Fleet) host the agents of a spec
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import sys
from pathlib import Path

# The owner of the robots `robots` makes (and of the API key `api-token` issues).
OWNER = "chaos-owner"


def _setup_django() -> None:
    os.environ.setdefault("DJANGO_SETTINGS_MODULE", "bridgeos_cloud.settings")
    import django

    django.setup()


def create_robots_here(prefix: str, count: int) -> list[tuple[str, str]]:
    """Create fresh robots through the cloud's own service; return (id, token) pairs."""
    _setup_django()
    from django.contrib.auth import get_user_model

    from robots.models import Robot
    from robots.services import create_robot

    Robot.objects.filter(id__startswith=f"{prefix}-").delete()
    owner, _ = get_user_model().objects.get_or_create(username=OWNER)
    pairs = []
    for i in range(count):
        robot, token = create_robot(f"{prefix}-{i:04d}", owner)
        pairs.append((robot.id, token))
    return pairs


def create_robot_here(spec: dict) -> dict[str, str]:
    """Create one robot of an owner of its own, with its config and Skills; return its token and an API key."""
    _setup_django()
    from django.contrib.auth import get_user_model

    from bridgeos_agent.skillconfig import parse_skill_config
    from robots.models import Robot
    from robots.services import create_robot, issue_api_token, update_robot_config
    from skills.services import add_skill

    Robot.objects.filter(id=spec["robot"]).delete()
    owner, _ = get_user_model().objects.get_or_create(username="chaos-" + spec["robot"])
    robot, token = create_robot(spec["robot"], owner)
    if spec.get("config"):
        update_robot_config(robot.id, spec["config"])
    for skill in spec["skills"]:
        add_skill(robot, parse_skill_config(skill).model_dump(mode="json"))
    return {"token": token, "api": issue_api_token(owner)[0]}


def api_token_here() -> str:
    """Issue a REST API token for the owner of the robots `robots` makes."""
    _setup_django()
    from django.contrib.auth import get_user_model

    from robots.services import issue_api_token

    owner, _ = get_user_model().objects.get_or_create(username=OWNER)
    return issue_api_token(owner)[0]


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.chaos.rig")
    commands = parser.add_subparsers(dest="command", required=True)
    robots = commands.add_parser("robots", help="create robots and print [[id, token], ...]")
    robots.add_argument("--prefix", required=True)
    robots.add_argument("--count", type=int, required=True)
    commands.add_parser("robot", help="create the robot a JSON spec on stdin describes; print its tokens")
    commands.add_parser("api-token", help="print a REST API token of the robots' owner")
    fleet = commands.add_parser("fleet", help="host the agents of a fleet spec")
    fleet.add_argument("spec", type=Path)
    args = parser.parse_args(argv)
    if args.command == "robots":
        print(json.dumps(create_robots_here(args.prefix, args.count)))
    elif args.command == "robot":
        print(json.dumps(create_robot_here(json.loads(sys.stdin.read()))))
    elif args.command == "api-token":
        print(api_token_here())
    else:
        from benchmarks.chaos.rig.fleet import host_fleet

        logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s %(message)s", stream=sys.stderr)
        asyncio.run(host_fleet(json.loads(args.spec.read_text())))


if __name__ == "__main__":
    main(sys.argv[1:])
