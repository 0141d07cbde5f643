"""`bridgeos robots`: the fleet and one robot."""

from __future__ import annotations

import click

from ..output import fields, json_option, show, state, table
from . import url_path

ROBOT_COLUMNS = ["id", "name", "status", "connected", "last_seen", "labels", ("skills", "skill_ids")]


def with_skill_ids(robot: dict) -> dict:
    """Add the ids of a robot's Skills, for its table row."""
    return {**robot, "skill_ids": [skill["skill_id"] for skill in robot.get("skills") or []]}


@click.group()
def robots() -> None:
    """List and inspect robots (only those you may see)."""


@robots.command("ls")
@click.option("--connected/--offline", default=None, help="Only connected robots, or only offline ones.")
@click.option("-l", "--selector", help="Only robots whose labels match, e.g. site=lab,!retired.")
@json_option
def robots_ls(connected: bool | None, selector: str | None) -> None:
    """List your robots with their status and Skills.

    \b
    Examples:
      bridgeos robots ls
      bridgeos robots ls --connected -l site=lab
      bridgeos robots ls --json | jq -r '.[].id'
    """
    found = (
        state()
        .api()
        .get("/api/robot", connected=None if connected is None else str(connected).lower(), selector=selector)
    )
    show(found, lambda rows: table([with_skill_ids(robot) for robot in rows], ROBOT_COLUMNS, empty="No robots."))


@robots.command("show")
@click.argument("robot")
@json_option
def robots_show(robot: str) -> None:
    """Show one robot: its state, labels, Skills and components.

    \b
    Examples:
      bridgeos robots show r1
      bridgeos robots show r1 --json | jq .config
    """
    found = state().api().get(f"/api/robot/{url_path(robot)}")

    def render(data: dict) -> None:
        fields(data, ["id", "name", "owner", "organization", "status", "connected", "last_seen", "labels", "ros2"])
        rows = [
            {"skill": skill["skill_id"], "skill_status": skill["status"], **component}
            for skill in data.get("skills") or []
            for component in skill.get("components") or [{}]
        ]
        if rows:
            click.echo()
            columns = ["skill", "skill_status", ("component", "component_id"), "location", "active_location", "status"]
            table(rows, columns)

    show(found, render)
