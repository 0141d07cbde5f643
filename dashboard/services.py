"""What the dashboard's pages read (a page of the fleet in a few queries) and what /ws/client/ answers."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

from django.contrib.auth.models import AbstractBaseUser
from django.db import connection
from django.db.models import (
    Case,
    Count,
    F,
    Func,
    IntegerField,
    OrderBy,
    OuterRef,
    Q,
    QuerySet,
    Subquery,
    Value,
    When,
)
from django.db.models.fields.json import KT
from django.db.models.functions import Coalesce
from django.utils import timezone
from pydantic import BaseModel
from pydantic import ValidationError as PydanticValidationError

from bridgeos_agent.errors import field_errors
from bridgeos_agent.protocol import Event, Location
from bridgeos_agent.robotconfig import parse_robot_config, robot_config_json_schema
from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_cloud.errors import NotFound
from monitoring.models import Metric
from monitoring.services import latest_metrics
from recordings.choices import RosProfile
from recordings.models import Recording
from recordings.services import DEFAULT_MAX_BYTES, DEFAULT_MAX_DURATION_S
from robots.access import Actor, robot_scope, robots_with, visible_robots
from robots.labels import Selector, selector_q
from robots.models import Robot
from robots.services import robot_config, update_robot_config
from rollouts.api.serializers import RolloutDetailSerializer
from rollouts.models import RolloutRobot
from rollouts.rolling import visible_rollouts
from skills.models import Component, Skill
from skills.services import component_state, skill_state, visible_templates
from skills.state import fleet_state_json
from teams.models import Organization
from teams.roles import Right

# Robot-wide series the fleet overview shows (points with no skill and no component):
# cpu, ram and battery in percent, bandwidth in Mbit/s. The robot page charts every series.
ROBOT_METRICS = ("cpu", "ram", "bandwidth", "battery")
# Older values are not "live" any more; the overview shows a dash instead.
LATEST_METRIC_MAX_AGE = timedelta(hours=1)
# The robots one fleet page shows: a bounded page renders in well under a second with 10,000 robots.
FLEET_PAGE_SIZE = 100
# The table's sort keys (a leading "-" sorts descending) and the robot states it filters by.
FLEET_SORTS = ("id", "connected", *ROBOT_METRICS, "offloading", "skills", "components", "seen")
FLEET_STATES = ("all", "online", "offline")
# Component statuses that count as running somewhere, in the table's "Runs on" and the fleet's counts.
ACTIVE_STATUSES = ("running", "starting", "migrating", "stopping")

CONFIG_PARSERS: dict[str, Callable[[Any], BaseModel]] = {"skill": parse_skill_config, "robot": parse_robot_config}

# A rollout's robot statuses, in the order a robot goes through them.
STATUSES = RolloutRobot.Status.values

LATEST_SQL = """
SELECT r.id, n.name, m.value, extract(epoch FROM m.ts)
FROM unnest(%s::text[]) AS r(id)
CROSS JOIN unnest(%s::text[]) AS n(name)
CROSS JOIN LATERAL (
  SELECT value, ts FROM monitoring_metric
  WHERE robot_id = r.id AND name = n.name AND skill = '' AND component = '' AND ts >= %s
  ORDER BY ts DESC LIMIT 1
) m
"""


@dataclass(frozen=True)
class FleetQuery:
    """What the fleet page asks for: a search (ids and names, or a label selector), a state, an order, a page."""

    text: str = ""
    selector: Selector | None = None
    state: str = "all"
    sort: str = "id"
    page: int = 1
    # Why the search matches nothing (a malformed selector), shown beside the search box.
    error: str = ""


def fleet_page(actor: Actor, query: FleetQuery, *, size: int = FLEET_PAGE_SIZE) -> dict[str, Any]:
    """Return one page of the robots a request may see that match a query, how many match, and the fleet's counts."""
    robots = visible_robots(actor)
    condition = _matching(query)
    # The whole fleet's counts and the matches' in one pass over the robots, not counted from rows.
    counts = robots.aggregate(
        robots=Count("pk"),
        online=Count("pk", filter=Q(connected=True)),
        # No search and every state: an empty condition, which cannot be a FILTER clause.
        matching=Count("pk", filter=condition) if condition else Count("pk"),
    )
    # A malformed selector matches nothing; the page says why.
    matches = 0 if query.error else counts["matching"]
    pages = max(1, -(-matches // size))
    page = min(query.page, pages)
    offset = (page - 1) * size
    rows = []
    if matches:
        ordered = robots.filter(condition).order_by(*_fleet_order(query.sort))
        rows = robot_rows(ordered[offset : offset + size])
    return {
        "robots": rows,
        "count": matches,
        "page": page,
        "pages": pages,
        "offset": offset,
        "size": size,
        "summary": {"robots": counts["robots"], "online": counts["online"], **_component_counts(actor)},
        "query": {"q": query.text, "state": query.state, "sort": query.sort},
        "error": query.error,
    }


def _matching(query: FleetQuery) -> Q:
    """Return the condition a robot meets to match the query's search and state (empty: every robot)."""
    condition = Q()
    if query.selector is not None:
        condition &= selector_q(query.selector)
    elif query.text:
        condition &= Q(id__icontains=query.text) | Q(name__icontains=query.text)
    if query.state != "all":
        condition &= Q(connected=query.state == "online")
    return condition


def _fleet_order(sort: str) -> list[OrderBy]:
    """Return the ORDER BY of a fleet sort key (``-key`` descending), ties in id order as the table has them."""
    key = sort.removeprefix("-")
    keys: list[Any]
    if key in ROBOT_METRICS:
        since = timezone.now() - LATEST_METRIC_MAX_AGE
        # A robot without a value in the last hour sorts as -1, below every measured one.
        latest = Metric.objects.filter(
            robot_id=OuterRef("pk"), name=key, skill="", component="", ts__gte=since
        ).order_by("-ts")
        keys = [Coalesce(Subquery(latest.values("value")[:1]), Value(-1.0))]
    elif key == "connected":
        keys = [Case(When(connected=True, then=Value(0)), default=Value(1))]
    elif key == "offloading":
        keys = [KT("config__offloading")]
    elif key == "skills":
        keys = [_count_of(Skill.objects.filter(robot=OuterRef("pk")))]
    elif key == "components":
        cloud = Component.objects.filter(
            skill__robot=OuterRef("pk"), status__in=ACTIVE_STATUSES, active_location=Location.CLOUD
        )
        keys = [_count_of(cloud)]
    elif key == "seen":
        # Connected robots are the most recently seen of all, then by when each was last seen.
        keys = [F("connected"), F("last_seen")]
    else:
        keys = [F("id")]
    descending = sort.startswith("-")
    order = [k.desc(nulls_last=True) if descending else k.asc(nulls_first=True) for k in keys]
    return [*order, F("id").asc()]


def _count_of(rows: QuerySet[Any]) -> Subquery:
    """Return a correlated count of ``rows``, to sort by without grouping the robots."""
    # COUNT as a plain function, not an aggregate: Django adds no GROUP BY, so the subquery is one row.
    counted = rows.order_by().annotate(n=Func(F("pk"), function="COUNT", output_field=IntegerField()))
    return Subquery(counted.values("n"))


def _component_counts(actor: Actor) -> dict[str, int]:
    """Count the Skills of the robots a request may see and their components running on the robot and in the cloud."""
    scope = robot_scope(actor)
    skills = Skill.objects.all() if scope is None else Skill.objects.filter(robot__in=scope)
    active = Component.objects.filter(status__in=ACTIVE_STATUSES)
    if scope is not None:
        active = active.filter(skill__robot__in=scope)
    counted = active.aggregate(
        on_robot=Count("pk", filter=Q(active_location=Location.ROBOT)),
        on_cloud=Count("pk", filter=Q(active_location=Location.CLOUD)),
    )
    return {"skills": skills.count(), **counted}


def robot_rows(robots: QuerySet[Robot]) -> list[dict[str, Any]]:
    """Return robots, in their order, each with its skills' components and latest robot metrics."""
    rows = list(
        robots.annotate(offloading=KT("config__offloading")).values(
            "id", "name", "labels", "status", "connected", "last_seen", "offloading"
        )
    )
    ids = [row["id"] for row in rows]
    skills: dict[str, list[dict[str, Any]]] = {}
    by_pk: dict[int, dict[str, Any]] = {}
    for pk, robot_id, skill_id, status in (
        Skill.objects.filter(robot_id__in=ids)
        .order_by("robot_id", "skill_id")
        .values_list("pk", "robot_id", "skill_id", "status")
    ):
        skill = {"skill_id": skill_id, "status": status, "components": []}
        by_pk[pk] = skill
        skills.setdefault(robot_id, []).append(skill)
    for skill_pk, component_id, location, active_location, status in (
        Component.objects.filter(skill_id__in=by_pk)
        .order_by("skill_id", "component_id")
        .values_list("skill_id", "component_id", "location", "active_location", "status")
    ):
        by_pk[skill_pk]["components"].append(
            {"component_id": component_id, "location": location, "active_location": active_location, "status": status}
        )
    metrics = latest_robot_metrics(ids, ROBOT_METRICS)
    for row in rows:
        row["skills"] = skills.get(row["id"], [])
        row["metrics"] = metrics.get(row["id"], {})
    return rows


def robots_out_of_sight(actor: Actor, robot_ids: Iterable[str]) -> set[str]:
    """Return those of the robots that the request may not see (or that do not exist)."""
    wanted = set(robot_ids)
    return wanted - set(visible_robots(actor).filter(id__in=wanted).values_list("id", flat=True))


def latest_robot_metrics(
    robot_ids: list[str], names: Iterable[str], *, now: datetime | None = None
) -> dict[str, dict[str, list[float]]]:
    """Return the latest robot-wide value of each named series: {robot: {name: [value, ts]}}."""
    names = list(names)
    if not robot_ids or not names:
        return {}
    since = (now or timezone.now()) - LATEST_METRIC_MAX_AGE
    latest: dict[str, dict[str, list[float]]] = {}
    if connection.vendor == "postgresql":
        # One index probe per (robot, name) on metric_robot_name_ts, however long the history.
        with connection.cursor() as cursor:
            cursor.execute(LATEST_SQL, [robot_ids, names, since])
            for robot_id, name, value, ts in cursor.fetchall():
                latest.setdefault(robot_id, {})[name] = [value, float(ts)]
        return latest
    points = Metric.objects.filter(robot_id__in=robot_ids, name__in=names, skill="", component="", ts__gte=since)
    for robot_id, name, value, ts in points.order_by("-ts").values_list("robot_id", "name", "value", "ts")[:100_000]:
        latest.setdefault(robot_id, {}).setdefault(name, [value, ts.timestamp()])
    return latest


def robot_state(user: AbstractBaseUser, robot_id: str) -> dict[str, Any] | None:
    """Return one of the user's robots as the Robot API renders it, components named from their config."""
    found = json.loads(fleet_state_json(visible_robots(user).filter(id=robot_id)))
    if not found:
        return None
    state = found[0]
    configs = dict(Skill.objects.filter(robot_id=robot_id).values_list("skill_id", "config"))
    for skill in state["skills"]:
        components = configs.get(skill["skill_id"], {}).get("components", {})
        for component in skill["components"]:
            component["name"] = components.get(component["component_id"], {}).get("name", "")
    return state


def robot_rights(actor: Actor, robot_id: str) -> dict[str, bool]:
    """Return what a request may do on a robot, so its page shows only those buttons (the API refuses the rest)."""
    organization_id = visible_robots(actor).filter(id=robot_id).values_list("organization_id", flat=True).first()
    if organization_id is None:
        return {"command": False, "develop": False, "administer": False}
    return {
        "command": actor.may(organization_id, Right.COMMAND),
        "develop": actor.may(organization_id, Right.DEVELOP),
        "administer": actor.may(organization_id, Right.ADMINISTER),
    }


def robot_choices(user: AbstractBaseUser) -> QuerySet[Robot]:
    """Return the ids and names of the robots a user may pick in a form."""
    return visible_robots(user).order_by("id").only("id", "name")


def robots_to_develop(actor: Actor) -> QuerySet[Robot]:
    """Return the robots a request may add Skills to (a developer's right), for the catalog's forms."""
    return robots_with(actor, Right.DEVELOP).order_by("id").only("id", "name")


def template_organizations(actor: Actor) -> list[Organization]:
    """Return the organizations a request may keep templates in, the picked one first."""
    reached = actor.organization_ids()
    # Staff reach every organization; they keep templates in their own ones (and the cloud's catalog).
    ids = [o for o in (list(actor.roles()) if reached is None else reached) if actor.may(o, Right.DEVELOP)]
    found = list(Organization.objects.filter(id__in=ids).order_by("slug"))
    return sorted(found, key=lambda o: o.id != actor.organization_id)


def namespaces(actor: Actor) -> list[str]:
    """Return the registry namespaces (organization slugs) a request reaches, the picked or personal one first."""
    reached = actor.organization_ids()
    ids = list(actor.roles()) if reached is None else reached
    found = Organization.objects.filter(id__in=ids).order_by("slug").values_list("id", "slug", "personal_of_id")
    rows = list(found)
    # The picked organization's first, else the user's own: the page's push example uses it.
    rows.sort(key=lambda row: (row[0] != actor.organization_id, row[2] != actor.user.pk))
    return [slug for _, slug, _ in rows]


def skill_and_component_ids(user: AbstractBaseUser) -> tuple[list[str], list[str]]:
    """Return the distinct skill ids and component ids on the user's robots, for filter suggestions."""
    robots = visible_robots(user)
    skill_ids = Skill.objects.filter(robot__in=robots).values_list("skill_id", flat=True).distinct()
    component_ids = Component.objects.filter(skill__robot__in=robots).values_list("component_id", flat=True).distinct()
    return sorted(skill_ids), sorted(component_ids)


def catalog(actor: Actor) -> list[dict[str, Any]]:
    """Return the Skill templates a request sees with the components each brings and where they may run."""
    templates = []
    for template in visible_templates(actor).order_by("name", "pk"):
        components = [
            {"component_id": cid, "name": c.get("name") or cid, "location": c.get("location", "robot")}
            for cid, c in template.config.get("components", {}).items()
        ]
        templates.append(
            {
                "id": template.pk,
                "name": template.name,
                "organization": template.organization.slug if template.organization else None,
                "description": template.description,
                "tags": template.tags,
                "skill_id": template.config.get("skill_id", ""),
                "policy": template.config.get("manager", {}).get("policy", ""),
                "components": components,
            }
        )
    return templates


def validate_config(kind: str, data: Any) -> tuple[dict[str, Any] | None, dict[str, list[str]]]:
    """Check a Skill or robot config against the shared schema.

    Return the normalised config and no errors, or None and the messages of every
    offending field keyed by its dotted path (``components.detector.resources.cpu``).
    """
    try:
        model = CONFIG_PARSERS[kind](data)
    except PydanticValidationError as exc:
        return None, field_errors(exc)
    return model.model_dump(mode="json"), {}


def robot_config_choices() -> dict[str, list[str]]:
    """Return the allowed values of the robot config's enumerated fields, from the shared schema."""
    properties = robot_config_json_schema()["properties"]
    return {name: list(properties[name]["enum"]) for name in ("heuristic", "offloading")}


# --------------------------------------------------------------------------- client commands (/ws/client/)


def store_config_change(event: str, robot_id: str, p: Any) -> None:
    """Store a client's change of a robot's config before it is relayed."""
    changes = dict(p.changes) if event == Event.ROBOT_CONFIG_UPDATE else {"offloading": p.mode}
    update_robot_config(robot_id, changes)


def answer_from_database(event: str, robot_id: str, p: Any) -> tuple[Event, dict[str, Any]]:
    """Answer a client's request from the cloud's own records; return the reply event and data."""
    if event == Event.ROBOT_CONFIG_GET:
        return Event.ROBOT_CONFIG, {"robot": robot_id, "config": robot_config(robot_id)}
    if event == Event.OFFLOADING_GET:
        return Event.OFFLOADING, {"robot": robot_id, "mode": robot_config(robot_id)["offloading"]}
    if event == Event.SKILL_STATUS_GET:
        skill = skill_state(robot_id, p.skill)
        return Event.SKILL_STATUS, {"robot": robot_id, "skill": skill.skill_id, "status": skill.status}
    if event == Event.SKILL_CONFIG_GET:
        skill = skill_state(robot_id, p.skill)
        return Event.SKILL_CONFIG, {"robot": robot_id, "skill": skill.skill_id, "config": skill.config}
    if event == Event.COMPONENT_STATUS_GET:
        component = component_state(robot_id, p.skill, p.component)
        data = {"robot": robot_id, "skill": p.skill, "component": p.component, "status": component.status}
        if component.active_location:
            data["location"] = component.active_location
        return Event.COMPONENT_STATUS, data
    if event == Event.METRICS_GET:
        points = latest_metrics(
            robot_id, names=p.names, skill=p.skill, component=p.component, since=p.since, limit=p.limit or 100
        )
        return Event.METRICS, {"robot": robot_id, "metrics": points}
    raise NotFound(f"event {event!r} is not a request clients can make", field="event")


def robot_recordings(robot_id: str, *, limit: int = 50) -> list[Recording]:
    """Return a robot's newest MCAP recordings (the caller checked the user may see the robot)."""
    return list(Recording.objects.filter(robot_id=robot_id).order_by("-created_at")[:limit])


def recording_limits() -> dict[str, Any]:
    """Return what the robot page's recording form offers: the ROS profiles and the default limits."""
    return {
        "profiles": list(RosProfile.values),
        "max_mib": DEFAULT_MAX_BYTES // (1024 * 1024),
        "max_duration_s": int(DEFAULT_MAX_DURATION_S),
    }


ROLLOUTS_PER_PAGE = 100


def rollout_list(actor: Actor, before: int | None = None) -> tuple[list[dict[str, Any]], int | None]:
    """Return the newest rollouts a request reaches (older than ``before``), each with its robots counted by status.

    Also return the id to ask for the next, older page from (None: this is the last).
    """
    rollouts = visible_rollouts(actor).order_by("-id")
    if before is not None:
        rollouts = rollouts.filter(id__lt=before)
    found = list(rollouts[: ROLLOUTS_PER_PAGE + 1])
    older = found[ROLLOUTS_PER_PAGE - 1].id if len(found) > ROLLOUTS_PER_PAGE else None
    found = found[:ROLLOUTS_PER_PAGE]
    counted: dict[int, dict[str, int]] = {rollout.id: {} for rollout in found}
    members = (
        RolloutRobot.objects.filter(rollout_id__in=counted)
        .order_by()
        .values_list("rollout_id", "status")
        .annotate(robots=Count("id"))
    )
    for rollout_id, status, robots in members:
        counted[rollout_id][status] = robots
    rows = [
        {
            "rollout": rollout,
            # In the statuses' own order, the way a robot goes through them.
            "counts": [(status, counted[rollout.id][status]) for status in STATUSES if status in counted[rollout.id]],
            "robots": sum(counted[rollout.id].values()),
        }
        for rollout in found
    ]
    return rows, older


def rollout_detail(actor: Actor, rollout_id: int) -> tuple[dict[str, Any], bool] | None:
    """Return a rollout as the Robot API reads it, and whether the request may steer it; None if out of reach."""
    rollout = visible_rollouts(actor).filter(pk=rollout_id).first()
    if rollout is None:
        return None
    return dict(RolloutDetailSerializer(rollout).data), actor.may(rollout.organization_id, Right.DEVELOP)
