"""The state of robots, their skills and components, defined once.

The Robot API (/api/robot, /info routes), its OpenAPI document (the serializers in
`skills.api.serializers` take their fields from here), the dashboard and /ws/client/ all
show these shapes. PostgreSQL builds the JSON itself (a fleet of 100 robots carries
thousands of components); other databases get the same document from rows.
"""

from __future__ import annotations

import json
import threading
from collections import OrderedDict
from typing import Any

from django.conf import settings
from django.core.serializers.json import DjangoJSONEncoder
from django.db import connection
from django.db.models import QuerySet

from robots.models import Robot

from .models import Component, Skill

# The fields of each level of a robot's state, in the order they are shown. A robot's state
# also carries its "skills" (each with its "components"); its owner is the username of who added
# it (null once they are gone) and its organization the slug of the organization it belongs to.
ROBOT_FIELDS = (
    "id",
    "name",
    "owner",
    "organization",
    "labels",
    "status",
    "connected",
    "last_seen",
    "ros_master",
    "ros2",
    "config",
)
SKILL_FIELDS = ("skill_id", "name", "status", "updated_at")
COMPONENT_FIELDS = (
    "component_id",
    "location",
    "active_location",
    "status",
    "message",
    "container",
    "resources",
    "updated_at",
)


def _columns(alias: str, fields: tuple[str, ...]) -> str:
    return ", ".join(f"{alias}.{field}" for field in fields)


JOINED = {"owner": "u.username", "organization": "o.slug"}
ROBOT_COLUMNS = ", ".join(f"{JOINED[f]} AS {f}" if f in JOINED else f"ro.{f}" for f in ROBOT_FIELDS)
# The rows a robot's state names besides its own: who added it, and its organization.
ROBOT_JOINS = "LEFT JOIN auth_user u ON u.id = ro.owner_id JOIN teams_organization o ON o.id = ro.organization_id"
SKILL_COLUMNS = _columns("sk", SKILL_FIELDS)
COMPONENT_COLUMNS = _columns("co", COMPONENT_FIELDS)


# --------------------------------------------------------------------------- as rows (any database)


def fleet_state(robots: QuerySet[Robot]) -> list[dict[str, Any]]:
    """Return robots with their skills and components as plain data, in three queries.

    Built from rows rather than model instances and serializers: a fleet of 100 robots
    carries thousands of components, and instances cost ten times more per row.
    """
    related = {"owner": "owner__username", "organization": "organization__slug"}
    robot_fields = [related.get(f, f) for f in ROBOT_FIELDS]
    robot_rows = list(robots.order_by("id").values(*robot_fields))
    skill_rows = Skill.objects.filter(robot__in=robots).order_by("robot_id", "skill_id")
    component_rows = Component.objects.filter(skill__robot__in=robots).order_by("skill_id", "component_id")
    components: dict[int, list[dict[str, Any]]] = {}
    for row in component_rows.values("skill_id", *COMPONENT_FIELDS):
        components.setdefault(row.pop("skill_id"), []).append(row)
    skills: dict[str, list[dict[str, Any]]] = {}
    for row in skill_rows.values("id", "robot_id", *SKILL_FIELDS):
        row["components"] = components.get(row.pop("id"), [])
        skills.setdefault(row.pop("robot_id"), []).append(row)
    states = []
    for row in robot_rows:
        row["owner"] = row.pop("owner__username")
        row["organization"] = row.pop("organization__slug")
        states.append({**{field: row[field] for field in ROBOT_FIELDS}, "skills": skills.get(row["id"], [])})
    return states


def component_state(component: Component) -> dict[str, Any]:
    """Return one component's state from its row."""
    return {field: getattr(component, field) for field in COMPONENT_FIELDS}


# --------------------------------------------------------------------------- as JSON built by PostgreSQL

# A robot's state version: every row version its JSON is built from. An UPDATE writes a new
# row version (a new ctid, and a new xmin unless in the same transaction), so any change to the
# robot, its owner, its organization, its skills or their components, or any skill or component added or removed,
# changes the digest. Reading it costs ~2 ms for 2,500 components; building their JSON, ~14 ms.
ROBOT_VERSION_SQL = """md5(concat_ws(',', ro.xmin, ro.ctid, u.xmin, u.ctid, o.xmin, o.ctid, (
  SELECT string_agg(concat(sk.xmin, sk.ctid, ':', (
    SELECT string_agg(concat(co.xmin, co.ctid), ',' ORDER BY co.id)
    FROM skills_component co WHERE co.skill_id = sk.id)), ';' ORDER BY sk.id)
  FROM skills_skill sk WHERE sk.robot_id = ro.id)))"""

FLEET_VERSIONS_SQL = f"""
SELECT ro.id, {ROBOT_VERSION_SQL}
FROM robots_robot ro {ROBOT_JOINS}
WHERE ro.id IN ({{robots}}) ORDER BY ro.id
"""

# A robot's skills, each with its components, as a JSON array (`ro` is the robot's row).
SKILLS_JSON_SQL = f"""coalesce((SELECT json_agg(s ORDER BY s.skill_id) FROM (
      SELECT {SKILL_COLUMNS},
        coalesce((SELECT json_agg(c ORDER BY c.component_id) FROM (
          SELECT {COMPONENT_COLUMNS}
          FROM skills_component co WHERE co.skill_id = sk.id) c), '[]') AS components
      FROM skills_skill sk WHERE sk.robot_id = ro.id) s), '[]')"""


ROBOTS_JSON_SQL = f"""
SELECT ro.id, {ROBOT_VERSION_SQL}, row_to_json(r)::text
FROM robots_robot ro {ROBOT_JOINS}
CROSS JOIN LATERAL (SELECT {ROBOT_COLUMNS}, {SKILLS_JSON_SQL} AS skills) r
WHERE ro.id = ANY(%s)
"""

SKILL_JSON_SQL = f"""
SELECT json_build_object(
  'robot', sk.robot_id, 'skill_id', sk.skill_id, 'name', sk.name, 'status', sk.status, 'config', sk.config,
  'updated_at', sk.updated_at,
  'components', coalesce((SELECT json_agg(c ORDER BY c.component_id) FROM (
      SELECT {COMPONENT_COLUMNS} FROM skills_component co WHERE co.skill_id = sk.id) c), '[]')
)::text
FROM skills_skill sk WHERE sk.robot_id IN ({{robots}}) AND sk.robot_id = %s AND sk.skill_id = %s
"""

COMPONENT_JSON_SQL = """
SELECT json_build_object(
  'robot', sk.robot_id, 'skill', sk.skill_id, 'component_id', co.component_id, 'location', co.location,
  'active_location', co.active_location, 'status', co.status, 'message', co.message, 'container', co.container,
  'resources', co.resources, 'updated_at', co.updated_at, 'config', sk.config -> 'components' -> co.component_id
)::text
FROM skills_component co JOIN skills_skill sk ON sk.id = co.skill_id
WHERE sk.robot_id IN ({robots}) AND sk.robot_id = %s AND sk.skill_id = %s AND co.component_id = %s
"""


class RobotStateCache:
    """Keep each robot's state JSON in this process, revalidated against its row versions on every read.

    A read never serves stale state: it first asks the database for every robot's current
    version (one cheap query) and rebuilds only the robots whose version changed.
    """

    def __init__(self, max_bytes: int) -> None:
        self.max_bytes = max_bytes
        self._entries: OrderedDict[str, tuple[str, str]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    def render(self, robots: QuerySet[Robot]) -> str:
        """Return the robots' state as a JSON array, ordered by id."""
        subquery, params = robots.values("id").query.sql_with_params()
        with connection.cursor() as cursor:
            cursor.execute(FLEET_VERSIONS_SQL.format(robots=subquery), params)
            versions = cursor.fetchall()
            with self._lock:
                cached = {robot_id: self._entries.get(robot_id) for robot_id, _ in versions}
            stale = [robot_id for robot_id, version in versions if (cached[robot_id] or ("",))[0] != version]
            if stale:
                cursor.execute(ROBOTS_JSON_SQL, [stale])
                fresh = {robot_id: (version, text) for robot_id, version, text in cursor.fetchall()}
                cached.update(fresh)
                self._store(fresh)
        # A robot deleted between the two queries has no state any more: leave it out.
        return "[" + ",".join(entry[1] for entry in (cached[robot_id] for robot_id, _ in versions) if entry) + "]"

    def _store(self, fresh: dict[str, tuple[str, str]]) -> None:
        with self._lock:
            for robot_id, entry in fresh.items():
                old = self._entries.pop(robot_id, None)
                self._bytes += len(entry[1]) - (len(old[1]) if old else 0)
                self._entries[robot_id] = entry
            while self._bytes > self.max_bytes and self._entries:
                _, (_, text) = self._entries.popitem(last=False)
                self._bytes -= len(text)


robot_states = RobotStateCache(max_bytes=settings.BRIDGEOS["STATE_CACHE_BYTES"])


def fleet_state_json(robots: QuerySet[Robot]) -> str:
    """Return fleet_state() as JSON text, built by PostgreSQL and cached per robot where available."""
    if connection.vendor != "postgresql":
        return json.dumps(fleet_state(robots), cls=DjangoJSONEncoder, separators=(",", ":"))
    return robot_states.render(robots)


# What `fields=` may pick from a robot's state: its own fields and its skills (with their components).
FLEET_FIELDS = (*ROBOT_FIELDS, "skills")


def fleet_fields_json(robots: QuerySet[Robot], fields: list[str]) -> str:
    """Return only these fields (of FLEET_FIELDS) of each robot's state as a JSON array ordered by id."""
    chosen = [field for field in FLEET_FIELDS if field in fields]
    if connection.vendor != "postgresql":
        states = [{field: state[field] for field in chosen} for state in fleet_state(robots)]
        return json.dumps(states, cls=DjangoJSONEncoder, separators=(",", ":"))
    # Built without the per-robot cache: a few columns of thousands of robots cost less than revalidating it.
    columns = {field: JOINED.get(field, f"ro.{field}") for field in ROBOT_FIELDS}
    columns["skills"] = SKILLS_JSON_SQL
    pairs = ", ".join(f"'{field}', {columns[field]}" for field in chosen)
    subquery, params = robots.values("id").query.sql_with_params()
    with connection.cursor() as cursor:
        cursor.execute(
            f"SELECT json_build_object({pairs})::text FROM robots_robot ro {ROBOT_JOINS}"
            f" WHERE ro.id IN ({subquery}) ORDER BY ro.id",
            params,
        )
        return "[" + ",".join(row[0] for row in cursor.fetchall()) + "]"


def skill_state_json(robots: QuerySet[Robot], robot_id: str, skill_id: str) -> str | None:
    """Return a skill of one of these robots with its config and components as JSON, or None."""
    if connection.vendor == "postgresql":
        return _one_json(SKILL_JSON_SQL, robots, [robot_id, skill_id])
    skill = Skill.objects.filter(robot__in=robots, robot_id=robot_id, skill_id=skill_id).first()
    if skill is None:
        return None
    state = {
        "robot": skill.robot_id,
        "skill_id": skill.skill_id,
        "name": skill.name,
        "status": skill.status,
        "config": skill.config,
        "updated_at": skill.updated_at,
        "components": [component_state(c) for c in skill.components.order_by("component_id")],
    }
    return json.dumps(state, cls=DjangoJSONEncoder)


def component_state_json(robots: QuerySet[Robot], robot_id: str, skill_id: str, component_id: str) -> str | None:
    """Return a component of one of these robots with its part of the Skill config as JSON, or None."""
    if connection.vendor == "postgresql":
        return _one_json(COMPONENT_JSON_SQL, robots, [robot_id, skill_id, component_id])
    component = (
        Component.objects.select_related("skill")
        .filter(skill__robot__in=robots, skill__robot_id=robot_id, skill__skill_id=skill_id, component_id=component_id)
        .first()
    )
    if component is None:
        return None
    state = {
        "robot": robot_id,
        "skill": skill_id,
        **component_state(component),
        "config": component.skill.config["components"].get(component_id),
    }
    return json.dumps(state, cls=DjangoJSONEncoder)


def _one_json(sql: str, robots: QuerySet[Robot], params: list[str]) -> str | None:
    """Run a query building one JSON document, restricted to a queryset of robots."""
    subquery, robot_params = robots.values("id").query.sql_with_params()
    with connection.cursor() as cursor:
        cursor.execute(sql.format(robots=subquery), [*robot_params, *params])
        row = cursor.fetchone()
    return row[0] if row else None
