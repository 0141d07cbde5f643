"""`bridgeos skills` and `bridgeos components`: a robot's Skills and their components."""

from __future__ import annotations

from typing import Any

import click

from ..errors import API_ERROR, CliError
from ..output import fields, json_option, show, state, table
from . import load_json_file, split_path, url_path

COMPONENT_COLUMNS = [
    ("component", "component_id"),
    "location",
    "active_location",
    "status",
    "message",
    "updated_at",
]
WAIT_HELP = "Seconds to wait for the robot's answer (default 5, at most 60)."


def wait_option(function: Any) -> Any:
    return click.option("--wait", type=click.FloatRange(0, 60, min_open=True), help=WAIT_HELP)(function)


def command_result(result: dict) -> None:
    """Print a relayed command's outcome; a robot's refusal ends the command with exit code 1."""
    reply = result.get("reply") or {}
    if state().json:
        show(result, lambda _: None)
    elif result.get("accepted"):
        click.echo(f"{result.get('event', 'command')} accepted by {result.get('robot')}.")
    if not result.get("accepted"):
        data = reply.get("data") or {}
        where = f" ({data['field']})" if data.get("field") else ""
        raise CliError(f"The robot refused: {data.get('message', reply)}{where}", API_ERROR)


@click.group()
def skills() -> None:
    """List, add, remove, start and stop a robot's Skills."""


@skills.command("ls")
@click.argument("robot")
@json_option
def skills_ls(robot: str) -> None:
    """List the Skills of ROBOT with their status and components.

    \b
    Examples:
      bridgeos skills ls r1
      bridgeos skills ls r1 --json | jq -r '.[].skill_id'
    """
    found = state().api().get(f"/api/robot/{url_path(robot)}")["skills"]

    def render(rows: list[dict]) -> None:
        listed = [{**skill, "components": [c["component_id"] for c in skill.get("components", [])]} for skill in rows]
        table(listed, [("skill", "skill_id"), "name", "status", "components", "updated_at"], empty="No Skills.")

    show(found, render)


@skills.command("show")
@click.argument("path", metavar="ROBOT/SKILL")
@json_option
def skills_show(path: str) -> None:
    """Show one Skill: its status and each component's location and status.

    \b
    Example:
      bridgeos skills show r1/people-detection
    """
    robot, skill = split_path(path, least=2, most=2, what="ROBOT/SKILL")
    found = state().api().get(f"/api/robot/{url_path(robot, 'skill', skill)}/info")

    def render(data: dict) -> None:
        fields(data, ["robot", "skill_id", "name", "status", "updated_at"])
        click.echo()
        table(data.get("components") or [], COMPONENT_COLUMNS)

    show(found, render)


@skills.command("add")
@click.argument("robot")
@click.option("-f", "--config", "config_file", help="A Skill config file (JSON; `-` reads stdin).")
@click.option("-t", "--template", type=int, help="The id of a catalog template instead (see the dashboard).")
@json_option
def skills_add(robot: str, config_file: str | None, template: int | None) -> None:
    """Add a Skill to ROBOT from a config file or a catalog template.

    \b
    Examples:
      bridgeos skills add r1 -f people-detection.json
      bridgeos skills add r1 --template 3
    """
    if (config_file is None) == (template is None):
        raise click.UsageError("Give exactly one of --config or --template.")
    body = {"config": load_json_file(config_file, "--config")} if config_file else {"template": template}
    added = state().api().post(f"/api/robot/{url_path(robot)}/skill/add", body)
    show(added, lambda data: click.echo(f"Skill {data['skill_id']} added to {data['robot']} ({data['status']})."))


@skills.command("remove")
@click.argument("path", metavar="ROBOT/SKILL")
@json_option
def skills_remove(path: str) -> None:
    """Remove a stopped Skill from its robot.

    \b
    Example:
      bridgeos skills remove r1/people-detection
    """
    robot, skill = split_path(path, least=2, most=2, what="ROBOT/SKILL")
    state().api().post(f"/api/robot/{url_path(robot)}/skill/remove", {"skill": skill})
    show({"robot": robot, "removed": skill}, lambda _: click.echo(f"Skill {skill} removed from {robot}."))


@skills.command("start")
@click.argument("path", metavar="ROBOT/SKILL")
@wait_option
@json_option
def skills_start(path: str, wait: float | None) -> None:
    """Launch a Skill on its robot.

    \b
    Example:
      bridgeos skills start r1/people-detection --wait 10
    """
    robot, skill = split_path(path, least=2, most=2, what="ROBOT/SKILL")
    command_result(state().api().post(f"/api/robot/{url_path(robot, 'skill', skill)}/start", wait=wait))


@skills.command("stop")
@click.argument("path", metavar="ROBOT/SKILL")
@wait_option
@json_option
def skills_stop(path: str, wait: float | None) -> None:
    """Stop a Skill on its robot.

    \b
    Example:
      bridgeos skills stop r1/people-detection
    """
    robot, skill = split_path(path, least=2, most=2, what="ROBOT/SKILL")
    command_result(state().api().post(f"/api/robot/{url_path(robot, 'skill', skill)}/stop", wait=wait))


@click.group()
def components() -> None:
    """Inspect, start, stop and migrate a Skill's components."""


def component_url(path: str) -> str:
    robot, skill, component = split_path(path, least=3, most=3, what="ROBOT/SKILL/COMPONENT")
    return f"/api/robot/{url_path(robot, 'skill', skill, 'component', component)}"


LOCATION = click.Choice(["robot", "cloud"])


@components.command("show")
@click.argument("path", metavar="ROBOT/SKILL/COMPONENT")
@json_option
def components_show(path: str) -> None:
    """Show a component: where it may and does run, its status and containers.

    \b
    Example:
      bridgeos components show r1/people-detection/detector
    """
    found = state().api().get(f"{component_url(path)}/info")
    keys = ["robot", "skill", "component_id", "location", "active_location", "status", "message", "updated_at"]
    show(found, lambda data: fields(data, keys))


@components.command("start")
@click.argument("path", metavar="ROBOT/SKILL/COMPONENT")
@click.option("--at", "location", type=LOCATION, required=True, help="Where to start it.")
@wait_option
@json_option
def components_start(path: str, location: str, wait: float | None) -> None:
    """Start a component on the robot or in the cloud.

    \b
    Example:
      bridgeos components start r1/people-detection/detector --at cloud
    """
    command_result(state().api().post(f"{component_url(path)}/start", {"location": location}, wait=wait))


@components.command("stop")
@click.argument("path", metavar="ROBOT/SKILL/COMPONENT")
@click.option("--at", "location", type=LOCATION, help="Stop only this instance (default: wherever it runs).")
@wait_option
@json_option
def components_stop(path: str, location: str | None, wait: float | None) -> None:
    """Stop a component.

    \b
    Example:
      bridgeos components stop r1/people-detection/detector
    """
    body = {"location": location} if location else {}
    command_result(state().api().post(f"{component_url(path)}/stop", body, wait=wait))


@components.command("migrate")
@click.argument("path", metavar="ROBOT/SKILL/COMPONENT")
@click.option("--to", "location", type=LOCATION, help="Target side (default: the other side of where it runs).")
@wait_option
@json_option
def components_migrate(path: str, location: str | None, wait: float | None) -> None:
    """Move a running component to the cloud or back to the robot, while it runs.

    \b
    Examples:
      bridgeos components migrate r1/people-detection/detector --to cloud
      bridgeos components migrate r1/people-detection/detector --to robot --wait 30
    """
    body = {"location": location} if location else {}
    command_result(state().api().post(f"{component_url(path)}/migrate", body, wait=wait))
