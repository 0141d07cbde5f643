"""`bridgeos logs`: component logs from the REST API, and followed live over /ws/client/."""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from typing import Any

import click

from ..output import emit_json, state
from . import split_path, url_path, when

LEVELS = ("debug", "info", "warning", "error", "critical")
PAGE = 1000  # the API's largest page
DEFAULT_TAIL = 100
# (skill, component, location): the newest seq printed of each, so a line pushed twice prints once.
Key = tuple[str, str, str]


def iso(ts: float | str) -> str:
    """Return a line's time as 2026-12-04T19:00:00.123Z, from unix seconds or ISO 8601."""
    moment = datetime.fromtimestamp(ts, UTC) if isinstance(ts, int | float) else datetime.fromisoformat(ts)
    return moment.astimezone(UTC).isoformat(timespec="milliseconds").replace("+00:00", "Z")


def render(line: dict[str, Any], *, robot: bool = False) -> str:
    """Format a line as the download does: time, location, stream, LEVEL, skill/component: text."""
    level = (line.get("level") or "-").upper()
    where = f"{line['robot']}/" if robot and line.get("robot") else ""
    return (
        f"{iso(line['ts'])} {line['location']} {line['stream']} {level} "
        f"{where}{line['skill']}/{line['component']}: {line['text']}"
    )


def matcher(level: str | None, grep: str | None, regex: bool, location: str | None) -> Callable[[dict], bool]:
    """Return the API's filters as a test of one pushed line (lines without a level count as info)."""
    lowest = LEVELS.index(level) if level else 0
    pattern = re.compile(grep if regex else re.escape(grep), re.IGNORECASE) if grep else None

    def matches(line: dict) -> bool:
        if LEVELS.index(line.get("level") or "info") < lowest:
            return False
        if location and line["location"] != location:
            return False
        return pattern is None or pattern.search(line["text"]) is not None

    return matches


def pushed_lines(data: dict[str, Any]) -> Iterator[dict[str, Any]]:
    """Yield the lines of a component_logs frame in the REST API's shape."""
    for line in data.get("lines") or []:
        yield {
            "robot": data.get("robot"),
            "skill": data["skill"],
            "component": data["component"],
            "location": data.get("location", "robot"),
            "seq": line["seq"],
            "ts": iso(line["ts"]),
            "stream": line["stream"],
            "level": line.get("level"),
            "text": line["text"],
        }


@click.command()
@click.argument("target", metavar="ROBOT[/SKILL[/COMPONENT]]")
@click.option("-f", "--follow", is_flag=True, help="Keep printing new lines as they arrive (Ctrl-C stops).")
@click.option("-n", "--tail", type=click.IntRange(0), help=f"The last N lines (default {DEFAULT_TAIL}).")
@click.option("--since", help="From this time: ISO 8601, unix seconds, or ago (30s, 10m, 2h, 1d).")
@click.option("--until", help="Up to this time (same forms as --since).")
@click.option("--level", type=click.Choice(LEVELS), help="Minimum level (lines without one count as info).")
@click.option("-g", "--grep", "query", help="Only lines containing this text (case-insensitive).")
@click.option("-E", "--regex", is_flag=True, help="--grep is a regular expression.")
@click.option("--location", type=click.Choice(["robot", "cloud"]), help="Only the robot's copy, or the cloud's.")
@click.option("--ring", is_flag=True, help="With -f: also ask the robot for lines it has not shipped yet.")
@click.option("--json", "as_json", is_flag=True, help="JSON: an array of lines; with -f one object per line.")
def logs(
    target: str,
    follow: bool,
    tail: int | None,
    since: str | None,
    until: str | None,
    level: str | None,
    query: str | None,
    regex: bool,
    location: str | None,
    ring: bool,
    as_json: bool,
) -> None:
    """Print the logs of a robot, one of its Skills, or one component.

    Without -n and with --since or --until, every line in the range is
    printed, oldest first; otherwise the last N lines. With -f the command
    keeps printing the lines the cloud pushes until interrupted.

    \b
    Examples:
      bridgeos logs r1
      bridgeos logs -f r1/people-detection/detector
      bridgeos logs r1/people-detection --since 1h --level warning -g timeout
      bridgeos logs r1 -g 'conn(ect|ection) refused' -E -n 500
      bridgeos logs r1/people-detection/detector --since 10m --json | jq -r '.[].text'
    """
    parts = split_path(target, least=1, most=3)
    state().json = as_json
    if regex and not query:
        raise click.UsageError("--regex needs --grep.")
    if follow and until:
        raise click.UsageError("--until and -f exclude each other: a followed log has no end.")
    if ring and not follow:
        raise click.UsageError("--ring goes with -f.")
    robot = parts[0]
    filters = {
        "skill": parts[1] if len(parts) > 1 else None,
        "component": parts[2] if len(parts) > 2 else None,
        "location": location,
        "since": when(since, "--since"),
        "until": when(until, "--until"),
        "level": level,
        "q": query,
        "regex": "true" if regex else None,
    }
    everything = tail is None and (since is not None or until is not None)
    count = DEFAULT_TAIL if tail is None else tail
    if follow:
        matches = matcher(level, query, regex, location)
        follow_logs(robot, filters, None if everything else count, matches, ring=ring, as_json=as_json)
        return
    lines = stored_lines(robot, filters, None if everything else count)
    if as_json:
        emit_json(lines)
    else:
        for line in lines:
            click.echo(render(line))


def stored_lines(robot: str, filters: dict[str, Any], count: int | None) -> list[dict[str, Any]]:
    """Return stored lines oldest first: every match (count None) or the newest ``count``."""
    if count == 0:
        return []
    path = f"/api/robot/{url_path(robot)}/logs"
    if count is None:
        lines = list(_pages(path, filters, "asc"))
    else:
        lines = list(_pages(path, filters, "desc", count))
        lines.reverse()
    return lines


def _pages(path: str, filters: dict[str, Any], order: str, count: int | None = None) -> Iterator[dict[str, Any]]:
    """Yield the lines of the logs API page after page (its `next` cursors), up to ``count``."""
    api = state().api()
    shown, dropped = 0, 0
    query: dict[str, Any] | None = {
        **{k: v for k, v in filters.items() if v is not None},
        "order": order,
        "limit": min(PAGE, count) if count else PAGE,
    }
    url: str | None = path
    while url:
        body = api.request("GET", url, params=query).json()
        dropped = max(dropped, body.get("dropped") or 0)
        for line in body["results"]:
            yield line
            shown += 1
            if count is not None and shown >= count:
                url = None
                break
        else:
            url, query = body.get("next"), None
    if dropped:
        click.echo(f"({dropped} lines were dropped on the robot before reaching the cloud)", err=True)


def follow_logs(
    robot: str,
    filters: dict[str, Any],
    count: int | None,
    matches: Callable[[dict], bool],
    *,
    ring: bool,
    as_json: bool,
) -> None:
    """Subscribe first, then print the stored tail, then every pushed line not printed yet."""
    from ..live import LiveClient

    request = {"robot": robot, "tail": 0, "ring": ring}
    request.update({k: filters[k] for k in ("skill", "component") if filters[k]})
    newest: dict[Key, int] = {}

    def emit(line: dict[str, Any]) -> None:
        line = {"robot": robot, **line}  # stored lines as pushed ones: each names its robot
        key = (line["skill"], line["component"], line["location"])
        if line["seq"] <= newest.get(key, 0):
            return
        newest[key] = line["seq"]
        if as_json:
            click.echo(json.dumps(line, separators=(",", ":")))
        else:
            click.echo(render(line))

    try:
        with LiveClient(state().api().login) as live:
            # Subscribed before reading the stored tail: a line stored in between is pushed, not lost.
            live.request("logs_subscribe", request)
            named = "/".join(part for part in (robot, filters["skill"], filters["component"]) if part)
            click.echo(f"Following the logs of {named} (Ctrl-C stops).", err=True)
            for line in stored_lines(robot, filters, count):
                emit(line)
            for envelope in live.frames():
                if envelope.get("event") != "component_logs" or envelope["data"].get("robot", robot) != robot:
                    continue
                data = envelope["data"]
                if data.get("dropped") and not as_json:
                    click.echo(f"({data['dropped']} lines of {data['skill']}/{data['component']} dropped)", err=True)
                for line in pushed_lines(data):
                    if matches(line):
                        emit(line)
    except KeyboardInterrupt:
        pass
