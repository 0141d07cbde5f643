"""`bridgeos metrics query`: metrics aggregated per time bucket (POST /api/database/query)."""

from __future__ import annotations

import click

from ..output import json_option, show, state, table
from . import when

AGGREGATES = ("avg", "min", "max", "last", "count")
COLUMNS = ["bucket", "robot", "skill", "component", "name", "value", "points"]


@click.group()
def metrics() -> None:
    """Query the metrics your robots and components report."""


@metrics.command("query")
@click.option("-r", "--robot", "robots", multiple=True, help="A robot (repeat for several; default: all yours).")
@click.option("--skill", help="Only this Skill's series.")
@click.option("--component", help="Only this component's series.")
@click.option("-m", "--name", "names", multiple=True, help="A metric name, e.g. cpu (repeat for several).")
@click.option("--since", help="From: ISO 8601, or ago (30s, 10m, 2h, 1d); default an hour before --until.")
@click.option("--until", help="Up to (same forms; default now).")
@click.option("-a", "--aggregate", type=click.Choice(AGGREGATES), default="avg", show_default=True)
@click.option("-b", "--bucket", type=click.IntRange(1, 86_400), help="Seconds per bucket (default: one bucket).")
@click.option("-n", "--limit", type=click.IntRange(1, 10_000), default=1000, show_default=True, help="At most N rows.")
@json_option
def metrics_query(
    robots: tuple[str, ...],
    skill: str | None,
    component: str | None,
    names: tuple[str, ...],
    since: str | None,
    until: str | None,
    aggregate: str,
    bucket: int | None,
    limit: int,
) -> None:
    """Aggregate metrics per time bucket, per robot, component and name.

    \b
    Examples:
      bridgeos metrics query -r r1 -m cpu -m ram --since 1h -b 60
      bridgeos metrics query -r r1 --skill people-detection -a max --json
    """
    body = {
        "kind": "metrics",
        "robots": list(robots) or None,
        "skill": skill,
        "component": component,
        "names": list(names) or None,
        "since": when(since, "--since"),
        "until": when(until, "--until"),
        "aggregate": aggregate,
        "bucket": bucket,
        "limit": limit,
    }
    answer = state().api().post("/api/database/query", {k: v for k, v in body.items() if v is not None})
    show(answer["results"], lambda rows: table(rows, COLUMNS, empty="No points in that range."))
