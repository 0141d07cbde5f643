"""`bridgeos events`: the event log from /api/events, and followed live (log_event frames of /ws/client/)."""

from __future__ import annotations

import json
from typing import Any

import click

from ..output import emit_json, state, table
from . import when

LEVELS = ("debug", "info", "warning", "error")
DEFAULT_COUNT = 50
COLUMNS = ["ts", "level", "kind", "robot", "skill", "component", "message"]


def line(event: dict[str, Any]) -> str:
    """Format one event for a followed log: time, level, kind, where, message."""
    where = "/".join(part for part in (event.get("robot"), event.get("skill"), event.get("component")) if part)
    return f"{event['ts']} {event['level'].upper():<7} {event['kind']} {where or '-'}: {event['message']}"


def matches(event: dict[str, Any], filters: dict[str, Any]) -> bool:
    """Tell whether a pushed event passes the filters the API would have applied."""
    for key in ("robot", "skill", "component", "kind"):
        if filters.get(key) and event.get(key) != filters[key]:
            return False
    level = filters.get("level")
    return not level or LEVELS.index(event.get("level", "info")) >= LEVELS.index(level)


@click.command()
@click.option("-f", "--follow", is_flag=True, help="Keep printing new events as they happen (Ctrl-C stops).")
@click.option("-r", "--robot", help="Only this robot's events.")
@click.option("--skill", help="Only this Skill's events.")
@click.option("--component", help="Only this component's events.")
@click.option("-k", "--kind", help="Only events of this kind (e.g. skill_status, component_status).")
@click.option("--level", type=click.Choice(LEVELS), help="Minimum level.")
@click.option("--since", help="From this time: ISO 8601, or ago (30s, 10m, 2h, 1d).")
@click.option("--until", help="Up to this time (same forms as --since).")
@click.option(
    "-n", "--limit", type=click.IntRange(0, 1000), default=DEFAULT_COUNT, show_default=True, help="The newest N events."
)
@click.option("--json", "as_json", is_flag=True, help="JSON: an array of events; with -f one object per line.")
def events(
    follow: bool,
    robot: str | None,
    skill: str | None,
    component: str | None,
    kind: str | None,
    level: str | None,
    since: str | None,
    until: str | None,
    limit: int,
    as_json: bool,
) -> None:
    """Print the event log of your robots, oldest of the N newest first.

    \b
    Examples:
      bridgeos events
      bridgeos events -r r1 --level warning --since 1d
      bridgeos events -f -r r1
      bridgeos events -k component_status --level error --json | jq '.[].data.lines'
    """
    if follow and until:
        raise click.UsageError("--until and -f exclude each other: a followed log has no end.")
    state().json = as_json
    filters = {
        "robot": robot,
        "skill": skill,
        "component": component,
        "kind": kind,
        "level": level,
        "since": when(since, "--since"),
        "until": when(until, "--until"),
    }
    if not follow:
        found = stored(filters, limit)
        if as_json:
            emit_json(found)
        else:
            table(found, COLUMNS, empty="No events.")
        return
    follow_events(filters, limit, as_json=as_json)


def stored(filters: dict[str, Any], limit: int) -> list[dict[str, Any]]:
    """Return the newest ``limit`` events matching, oldest first."""
    if limit == 0:
        return []
    found = list(state().api().pages("/api/events", limit=limit, **filters))
    found.reverse()
    return found


def follow_events(filters: dict[str, Any], limit: int, *, as_json: bool) -> None:
    """Connect first, then print the stored newest events, then each pushed log_event not printed yet."""
    from ..live import LiveClient

    seen: set[int] = set()

    def emit(event: dict[str, Any]) -> None:
        if event.get("id") in seen:
            return
        seen.add(event["id"])
        click.echo(json.dumps(event, separators=(",", ":")) if as_json else line(event))

    try:
        with LiveClient(state().api().login) as live:
            click.echo("Following the event log (Ctrl-C stops).", err=True)
            for event in stored(filters, limit):
                emit(event)
            for envelope in live.frames():
                if envelope.get("event") == "log_event" and matches(envelope["data"], filters):
                    emit(envelope["data"])
    except KeyboardInterrupt:
        pass
