"""`bridgeos releases` and `bridgeos rollouts`: immutable Skill releases, rolled out to labelled robots."""

from __future__ import annotations

from typing import Any

import click

from ..output import fields, json_option, show, state, table
from . import load_json_file

RELEASE_COLUMNS = ["id", "organization", "skill_id", "number", "name", "created_by", "created_at"]
ROLLOUT_COLUMNS = [
    "id",
    "organization",
    ("skill", "skill_id"),
    ("release", "release_number"),
    "selector",
    "state",
    "batch",
    "created_at",
]
ROLLOUT_FIELDS = [
    "id",
    "organization",
    "skill_id",
    "release",
    "release_number",
    "selector",
    "follow",
    "state",
    "reason",
    "batch",
    "batch_sizes",
    "created_by",
    "created_at",
    "finished_at",
]
ROBOT_COLUMNS = ["robot", "batch", "status", "reason", "started_at", "finished_at"]


@click.group()
def releases() -> None:
    """List, inspect and make Skill releases (immutable, images pinned by digest)."""


@releases.command("ls")
@click.option("--skill", help="Only this Skill's releases.")
@click.option("--organization", help="Only this organization's releases.")
@click.option("-n", "--limit", type=click.IntRange(1), default=100, show_default=True, help="The newest N.")
@json_option
def releases_ls(skill: str | None, organization: str | None, limit: int) -> None:
    """List releases, newest first.

    \b
    Examples:
      bridgeos releases ls --skill people-detection
      bridgeos releases ls --json | jq '.[0].id'
    """
    found = list(state().api().pages("/api/releases", limit=limit, skill=skill, organization=organization))
    show(found, lambda rows: table(rows, RELEASE_COLUMNS, empty="No releases."))


@releases.command("show")
@click.argument("release", type=int)
@json_option
def releases_show(release: int) -> None:
    """Show one release, its Skill config included (with --json).

    \b
    Example:
      bridgeos releases show 12
    """
    found = state().api().get(f"/api/releases/{release}")
    show(found, lambda data: fields(data, [*RELEASE_COLUMNS, "notes"]))


@releases.command("create")
@click.option("-f", "--config", "config_file", required=True, help="The Skill config (JSON; `-` reads stdin).")
@click.option("--name", default="", help="A name for people, e.g. v1.4.")
@click.option("--notes", default="", help="What changed.")
@click.option("--organization", help="The organization it belongs to (default: your token's, or your only one).")
@json_option
def releases_create(config_file: str, name: str, notes: str, organization: str | None) -> None:
    """Make the next release of the Skill a config describes.

    \b
    Example:
      bridgeos releases create -f people-detection.json --name v1.4 --notes "faster detector"
    """
    body: dict[str, Any] = {"config": load_json_file(config_file, "--config"), "name": name, "notes": notes}
    if organization:
        body["organization"] = organization
    made = state().api().post("/api/releases", body)
    show(made, lambda data: click.echo(f"Release {data['id']}: {data['skill_id']} #{data['number']}."))


@click.group()
def rollouts() -> None:
    """Roll a release out to the robots a label selector names, in batches; pause, resume, abort."""


@rollouts.command("ls")
@click.option("-n", "--limit", type=click.IntRange(1), default=100, show_default=True, help="The newest N.")
@json_option
def rollouts_ls(limit: int) -> None:
    """List rollouts, newest first.

    \b
    Examples:
      bridgeos rollouts ls
      bridgeos rollouts ls --json | jq '.[] | select(.state == "running") | .id'
    """
    found = list(state().api().pages("/api/rollouts", limit=limit))
    show(found, lambda rows: table(rows, ROLLOUT_COLUMNS, empty="No rollouts."))


def render_rollout(data: dict) -> None:
    """Print a rollout, then its robots when the answer lists them."""
    fields(data, ROLLOUT_FIELDS)
    if data.get("counts"):
        click.echo("counts:" + "".join(f" {status}={n}" for status, n in data["counts"].items()))
    if data.get("robots"):
        click.echo()
        table(data["robots"], ROBOT_COLUMNS)


@rollouts.command("show")
@click.argument("rollout", type=int)
@json_option
def rollouts_show(rollout: int) -> None:
    """Show a rollout: state, batches, counts and every robot's status.

    \b
    Example:
      bridgeos rollouts show 7
    """
    show(state().api().get(f"/api/rollouts/{rollout}"), render_rollout)


@rollouts.command("create")
@click.option("--release", type=click.IntRange(1), required=True, help="The id of the release to roll out.")
@click.option("-l", "--selector", required=True, help="The robots: labels they match, e.g. site=lab,!retired.")
@click.option("--follow", is_flag=True, help="Robots that join the group later get the release too.")
@click.option("--strategy", "strategy_file", help="A JSON file of the strategy (first, growth, soak_s, ...).")
@click.option("--gates", "gates_file", help='A JSON file of the health gates ({"conditions": [...]}).')
@json_option
def rollouts_create(
    release: int, selector: str, follow: bool, strategy_file: str | None, gates_file: str | None
) -> None:
    """Start rolling a release out to the robots a selector names.

    \b
    Examples:
      bridgeos rollouts create --release 12 -l site=lab
      bridgeos rollouts create --release 12 -l 'model=turtlebot,!retired' --strategy strategy.json --follow
    """
    body: dict[str, Any] = {"release": release, "selector": selector, "follow": follow}
    if strategy_file:
        body["strategy"] = load_json_file(strategy_file, "--strategy")
    if gates_file:
        body["gates"] = load_json_file(gates_file, "--gates")
    show(state().api().post("/api/rollouts", body), render_rollout)


def steer(action: str) -> click.Command:
    """Make the command that pauses, resumes or aborts a rollout."""

    @click.argument("rollout", type=int)
    @json_option
    def command(rollout: int) -> None:
        changed = state().api().post(f"/api/rollouts/{rollout}/{action}")
        show(changed, lambda data: click.echo(f"Rollout {data['id']}: {data['state']}."))

    command.__doc__ = {
        "pause": "Pause a rollout after its current batch.",
        "resume": "Resume a paused rollout.",
        "abort": "Abort a rollout: every robot it touched is rolled back.",
    }[action] + f"\n\n    \b\n    Example:\n      bridgeos rollouts {action} 7\n    "
    return rollouts.command(action)(command)


for _action in ("pause", "resume", "abort"):
    steer(_action)
