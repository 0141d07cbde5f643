"""Domain actions on skills: adding Skill configs to robots and applying what robots report."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from django.core.exceptions import ValidationError
from django.db import connection, transaction
from django.db.models import Q, QuerySet
from django.utils import timezone

from bridgeos_agent.protocol import ComponentStatusName, Event, Location, SkillStatusName
from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_cloud.errors import NotFound
from bridgeos_cloud.validation import validated_config
from monitoring import prometheus
from monitoring.choices import Level, Source
from monitoring.live import publish_on_commit
from monitoring.services import record_event, storable
from registry.pinning import pin_images
from robots.access import Actor
from robots.models import Robot
from robots.services import client_frame, push_to_robot
from teams.models import Organization

from .choices import COMPONENT_STATUS_CHOICES
from .cloud import orchestration
from .cloud.relay import relay_for_skill
from .models import CloudInstance, Component, Skill, SkillTemplate

if TYPE_CHECKING:
    from bridgeos_agent.protocol import OffloadingDecision


def add_skill(robot: Robot, config: dict[str, Any]) -> Skill:
    """Add a Skill and its components to a robot, all or nothing."""
    normalised = pin_images(validated_config(parse_skill_config, config), robot)
    skill_id = normalised["skill_id"]
    with transaction.atomic():
        if Skill.objects.filter(robot=robot, skill_id=skill_id).exists():
            raise ValidationError({"skill_id": [f"Robot {robot.id} already has a skill {skill_id!r}."]})
        skill = Skill.objects.create(robot=robot, skill_id=skill_id, name=normalised["skill"], config=normalised)
        Component.objects.bulk_create(
            Component(
                skill=skill,
                component_id=component_id,
                location=component["location"],
                resources=component.get("resources", {}),
            )
            for component_id, component in normalised["components"].items()
        )
        record_event(f"Skill {skill_id} added", robot_id=robot.id, skill=skill_id, kind="skill_added")
        # The robot, when connected, fetches the Skill's images now rather than at its first start.
        transaction.on_commit(
            lambda: push_to_robot(robot.id, Event.SKILL_CONFIG, {"skill": skill_id, "config": normalised}), robust=True
        )
    return skill


def set_skill_config(skill: Skill, config: dict[str, Any], *, stored: bool = False, tell: bool = True) -> None:
    """Replace a stopped or stopping Skill's config (a release installed or rolled back) and tell the robot.

    ``stored``: the config is one the cloud validated when it stored it (a release's, or the Skill's
    own before a rollout), so it is not parsed again for each of a rollout's robots. ``tell=False``:
    the order that follows (a start) carries the config itself.
    """
    normalised = config if stored else validated_config(parse_skill_config, config)
    skill.config, skill.name = normalised, normalised["skill"]
    skill.save(update_fields=["config", "name", "updated_at"])
    wanted = normalised["components"]
    placed = placement(normalised)
    known_placed = {
        cid: (loc, res) for cid, loc, res in skill.components.values_list("component_id", "location", "resources")
    }
    if placed == known_placed:
        # A new version of the same components (a release's usual change): nothing to add, drop or move.
        _tell_config(skill, normalised, tell)
        return
    skill.components.exclude(component_id__in=list(wanted)).delete()
    known = set(skill.components.values_list("component_id", flat=True))
    Component.objects.bulk_create(
        Component(skill=skill, component_id=cid, location=c["location"], resources=c.get("resources", {}))
        for cid, c in wanted.items()
        if cid not in known
    )
    for component in skill.components.all():
        spec = wanted[component.component_id]
        if component.location != spec["location"] or component.resources != spec.get("resources", {}):
            component.location, component.resources = spec["location"], spec.get("resources", {})
            component.save(update_fields=["location", "resources", "updated_at"])
    _tell_config(skill, normalised, tell)


def placement(config: dict[str, Any]) -> dict[str, tuple[str, Any]]:
    """Return which components a Skill config has, and where each may run with what resources."""
    return {cid: (c["location"], c.get("resources", {})) for cid, c in config["components"].items()}


def _tell_config(skill: Skill, config: dict[str, Any], tell: bool) -> None:
    if tell:
        robot_id, skill_id = skill.robot_id, skill.skill_id
        transaction.on_commit(
            lambda: push_to_robot(robot_id, Event.SKILL_CONFIG, {"skill": skill_id, "config": config}), robust=True
        )


def add_skill_from_template(robot: Robot, template: SkillTemplate) -> Skill:
    """Add the Skill of a catalog template to a robot."""
    return add_skill(robot, template.config)


def start_order(skill: Skill) -> dict[str, Any]:
    """Return the skill_start a robot gets: its config and the cloud relay it uses, if any (started on commit)."""
    with transaction.atomic():
        relay = relay_for_skill(skill)
    order: dict[str, Any] = {"skill": skill.skill_id, "config": skill.config}
    if relay is not None:
        order["cloud_relay"] = relay
    return order


# --------------------------------------------------------------------------- robot reports


def _skill(robot_id: str, skill_id: str) -> Skill:
    try:
        return Skill.objects.get(robot_id=robot_id, skill_id=skill_id)
    except Skill.DoesNotExist:
        raise NotFound(f"robot {robot_id} has no skill {skill_id!r}", field="data.skill") from None


def _component(robot_id: str, skill_id: str, component_id: str) -> Component:
    try:
        return Component.objects.select_for_update().get(
            skill__robot_id=robot_id, skill__skill_id=skill_id, component_id=component_id
        )
    except Component.DoesNotExist:
        _skill(robot_id, skill_id)
        raise NotFound(f"skill {skill_id!r} has no component {component_id!r}", field="data.component") from None


def _announce(robot_id: str, event: Event, data: dict[str, Any]) -> None:
    publish_on_commit(robot_id, client_frame(event, {"robot": robot_id, **data}))


def report_skill_status(robot_id: str, skill_id: str, status: str, message: str | None = None) -> None:
    """Record the status a robot reports for one of its skills."""
    with transaction.atomic(savepoint=False):  # no savepoint inside a frame's claim (robots.dbthreads)
        # One UPDATE in SQL (its row lock as a SELECT FOR UPDATE's), as a component's status is.
        with connection.cursor() as cursor:
            cursor.execute(
                f"UPDATE {Skill._meta.db_table} SET status = %s, updated_at = %s WHERE robot_id = %s AND skill_id = %s",
                [status, timezone.now(), robot_id, skill_id],
            )
            found = cursor.rowcount > 0
        if not found:
            raise NotFound(f"robot {robot_id} has no skill {skill_id!r}", field="data.skill")
        record_event(
            f"Skill {skill_id} is {status}" + (f": {message}" if message else ""),
            robot_id=robot_id,
            level=Level.ERROR if status == SkillStatusName.FAILED else Level.INFO,
            source=Source.ROBOT,
            kind=Event.SKILL_STATUS,
            skill=skill_id,
        )
        _announce(robot_id, Event.SKILL_STATUS, {"skill": skill_id, "status": status})


def _set_component_status(
    robot_id: str, skill_id: str, component_id: str, status: str, message: str, location: str | None
) -> bool:
    """Store a component's reported status in one statement; return whether the component exists.

    Written in SQL: the ORM's update through a join cost daphne more than the round trip itself,
    and a rollout's thousand robots each report a dozen of these per install.
    """
    component, skill = Component._meta.db_table, Skill._meta.db_table
    with connection.cursor() as cursor:
        cursor.execute(
            f"UPDATE {component} AS c SET status = %s, message = %s, "  # our table names; values as parameters
            f"active_location = COALESCE(%s, c.active_location), updated_at = %s "
            f"FROM {skill} AS s WHERE c.skill_id = s.id AND s.robot_id = %s AND s.skill_id = %s "
            f"AND c.component_id = %s",
            [status, message, location or None, timezone.now(), robot_id, skill_id, component_id],
        )
        return cursor.rowcount > 0


def report_component_status(
    robot_id: str,
    skill_id: str,
    component_id: str,
    status: str,
    location: str | None,
    message: str | None = None,
    *,
    last_lines: list[dict[str, Any]] | None = None,
) -> None:
    """Record the status a robot reports for a component (a crash's last lines go into its event's data)."""
    with transaction.atomic(savepoint=False):
        # The reason goes with the status it explains: a component that runs again has none.
        if not _set_component_status(robot_id, skill_id, component_id, status, message or "", location):
            _skill(robot_id, skill_id)
            raise NotFound(f"skill {skill_id!r} has no component {component_id!r}", field="data.component")
        record_event(
            f"Component {component_id} is {status}" + (f" on the {location}" if location else ""),
            robot_id=robot_id,
            level=Level.ERROR if status == ComponentStatusName.FAILED else Level.INFO,
            source=Source.ROBOT,
            kind=Event.COMPONENT_STATUS,
            skill=skill_id,
            component=component_id,
            data={
                "status": status,
                **({"message": message} if message else {}),
                **({"lines": last_lines} if last_lines is not None else {}),
            },
        )
        data = {"skill": skill_id, "component": component_id, "status": status}
        if location:
            data["location"] = location
        if message:
            data["message"] = message
        _announce(robot_id, Event.COMPONENT_STATUS, data)


def report_component_location(robot_id: str, skill_id: str, component_id: str, location: str) -> None:
    """Record where a component now runs."""
    with transaction.atomic(savepoint=False):
        component = _component(robot_id, skill_id, component_id)
        if component.location not in (location, Location.EITHER):
            raise NotFound(
                f"component {component_id!r} may only run on the {component.location}", field="data.location"
            )
        if component.active_location != location:
            component.active_location = location
            component.save(update_fields=["active_location", "updated_at"])
            record_event(
                f"Component {component_id} now runs on the {location}",
                robot_id=robot_id,
                source=Source.ROBOT,
                kind=Event.COMPONENT_LOCATION,
                skill=skill_id,
                component=component_id,
            )
        _announce(
            robot_id, Event.COMPONENT_LOCATION, {"skill": skill_id, "component": component_id, "location": location}
        )


def report_component_information(
    robot_id: str, skill_id: str, component_id: str, location: str, container: dict[str, Any]
) -> None:
    """Record what a robot reports about a component's container."""
    container = storable(container)  # the robot's own text: a NUL in it must not fail the frame
    with transaction.atomic(savepoint=False):
        component = _component(robot_id, skill_id, component_id)
        previous = component.container.get(location) or {}
        running = component.status == ComponentStatusName.RUNNING and component.active_location == location
        if running and _fetched_ahead(container):
            # A next version's image fetched while this one runs: the running container's details stay.
            container = {**previous, "pull": container["pull"]}
        component.container = {**component.container, location: container}
        component.save(update_fields=["container", "updated_at"])
        _announce(
            robot_id,
            Event.COMPONENT_INFORMATION,
            {"skill": skill_id, "component": component_id, "location": location, "container": container},
        )


def _fetched_ahead(container: dict[str, Any]) -> bool:
    """Tell whether a report says only how far an image's pull is (no container of it runs yet)."""
    return "pull" in container and not set(container) - {"runtime", "image", "pull"}


def report_offloading_decision(robot_id: str, decision: OffloadingDecision) -> None:
    """Log a move a Skill Manager decided (and how it went), and show it to clients."""
    data = decision.model_dump(mode="json", exclude={"robot"})
    with transaction.atomic(savepoint=False):
        _component(robot_id, decision.skill, decision.component)
        moved = decision.outcome == "moved"
        where = f"component {decision.component} from the {decision.location} to the {decision.target}"
        record_event(
            f"Skill Manager moved {where}" if moved else f"Skill Manager failed to move {where}: {decision.error}",
            robot_id=robot_id,
            level=Level.INFO if moved else Level.WARNING,
            source=Source.MANAGER,
            kind=Event.OFFLOADING_DECISION,
            skill=decision.skill,
            component=decision.component,
            data=data,
            ts=datetime.fromtimestamp(decision.decided_at, tz=UTC),
        )
        _announce(robot_id, Event.OFFLOADING_DECISION, data)


def report_skill_connect(robot_id: str, skill_id: str, manager_url: str | None) -> None:
    """Record that a Skill Manager connected to its Robot Controller."""
    with transaction.atomic(savepoint=False):
        _skill(robot_id, skill_id)
        record_event(
            f"Manager of skill {skill_id} connected",
            robot_id=robot_id,
            source=Source.MANAGER,
            kind=Event.SKILL_CONNECT,
            skill=skill_id,
            data={"manager_url": manager_url} if manager_url else None,
        )
        data = {"skill": skill_id, "manager_url": manager_url} if manager_url else {"skill": skill_id}
        _announce(robot_id, Event.SKILL_CONNECT, data)


def report_skill_config(robot_id: str, skill_id: str, config: dict[str, Any]) -> Skill:
    """Store the Skill config a robot holds locally, adding the skill if the cloud lacks it."""
    if config.get("skill_id", skill_id) != skill_id:
        raise ValidationError({"config": [f"skill_id: must be {skill_id!r}, the skill it is sent for"]})
    normalised = validated_config(parse_skill_config, {**config, "skill_id": skill_id})
    with transaction.atomic():
        skill = Skill.objects.select_for_update().filter(robot_id=robot_id, skill_id=skill_id).first()
        if skill is None:
            return add_skill(Robot.objects.get(id=robot_id), normalised)
        skill.config, skill.name = normalised, normalised["skill"]
        skill.save(update_fields=["config", "name", "updated_at"])
        known = set(skill.components.values_list("component_id", flat=True))
        Component.objects.bulk_create(
            Component(skill=skill, component_id=cid, location=c["location"], resources=c.get("resources", {}))
            for cid, c in normalised["components"].items()
            if cid not in known
        )
        _announce(robot_id, Event.SKILL_CONFIG, {"skill": skill_id, "config": normalised})
    return skill


def skill_state(robot_id: str, skill_id: str) -> Skill:
    """Return a robot's skill, or raise NotFound."""
    return _skill(robot_id, skill_id)


def request_cloud_component(robot_id: str, skill_id: str, component_id: str, action: str) -> None:
    """Record a robot's request to start or stop the cloud side of a component.

    The request is accepted and shown as pending in the cloud; the cloud runtime (the
    orchestration's Celery workers) launches or stops it once this commits, and tells the robot.
    A start that is a migration's first step leaves the component where it runs until the
    robot reports the move.
    """
    with transaction.atomic():
        component = _component(robot_id, skill_id, component_id)
        if action == "start" and component.location == Location.ROBOT:
            raise NotFound(f"component {component_id!r} may only run on the robot", field="data.location")
        migrating = component.status == ComponentStatusName.MIGRATING and component.active_location == Location.ROBOT
        if action == "start":
            orchestration.request_start(component)
            if migrating:
                record_event(
                    f"Cloud copy of {component_id} requested for its move to the cloud",
                    robot_id=robot_id,
                    source=Source.ROBOT,
                    kind="component_start",
                    skill=skill_id,
                    component=component_id,
                )
                return
            component.active_location = Location.CLOUD
            component.status = ComponentStatusName.PENDING
        elif component.active_location == Location.CLOUD:
            orchestration.request_stop(component)
            component.status = ComponentStatusName.STOPPED
        else:
            # Its cloud copy is being retired after a move to the robot: only the copy goes.
            orchestration.request_stop(component)
            return
        component.message = ""
        component.save(update_fields=["status", "message", "active_location", "updated_at"])
        record_event(
            f"Robot asks the cloud to {action} component {component_id}",
            robot_id=robot_id,
            source=Source.ROBOT,
            kind=f"component_{action}",
            skill=skill_id,
            component=component_id,
        )
        data = {"skill": skill_id, "component": component_id, "status": component.status}
        _announce(robot_id, Event.COMPONENT_STATUS, {**data, "location": Location.CLOUD.value})


def check_location(component: Component, location: str) -> None:
    """Refuse a location the component's config does not allow."""
    if component.location not in (location, Location.EITHER):
        raise ValidationError(
            {"location": [f"Component {component.component_id} may only run on the {component.location}."]}
        )


def migration_target(component: Component, location: str | None) -> str:
    """Return where a migration moves a component: the side asked for, else the other one; refuse what cannot be."""
    target = location
    if target is None:
        if not component.active_location:
            raise ValidationError({"location": ["The component is not running; say where to move it."]})
        target = Location.CLOUD if component.active_location == Location.ROBOT else Location.ROBOT
    check_location(component, target)
    if target == component.active_location:
        raise ValidationError({"location": [f"Component {component.component_id} runs on the {target} already."]})
    return str(target)


def component_state(robot_id: str, skill_id: str, component_id: str) -> Component:
    """Return a skill's component, or raise NotFound."""
    with transaction.atomic():
        return _component(robot_id, skill_id, component_id)


def remove_skill(skill: Skill) -> bool:
    """Remove a skill that is not running; return False (changing nothing) if it runs."""
    with transaction.atomic():
        locked = Skill.objects.select_for_update().get(pk=skill.pk)
        if locked.status in (SkillStatusName.RUNNING, SkillStatusName.STARTING, SkillStatusName.STOPPING):
            return False
        locked.delete()
        record_event(
            f"Skill {skill.skill_id} removed", robot_id=skill.robot_id, skill=skill.skill_id, kind="skill_removed"
        )
    return True


def create_template(
    *,
    name: str,
    config: dict[str, Any],
    description: str = "",
    tags: list[str] | None = None,
    organization: Organization | None = None,
) -> SkillTemplate:
    """Add a Skill config to an organization's templates, or to the cloud's catalog (no organization)."""
    if SkillTemplate.objects.filter(organization=organization, name=name).exists():
        raise ValidationError({"name": ["A template with this name exists already."]})
    return SkillTemplate.objects.create(
        name=name, config=config, description=description, tags=tags or [], organization=organization
    )


def write_cloud_copy_families(lines: list[str]) -> None:
    """Add cloud copies by state and their restarts to a /metrics scrape (read from PostgreSQL)."""
    counts = dict.fromkeys((value for value, _ in COMPONENT_STATUS_CHOICES), 0)
    restarts = 0
    for status, copy_restarts in CloudInstance.objects.values_list("status", "restarts"):
        counts[status] = counts.get(status, 0) + 1
        restarts += copy_restarts
    prometheus.family(lines, "bridgeos_cloud_copies", "Cloud copies of components by state.")
    lines.extend(
        f'bridgeos_cloud_copies{{state="{prometheus.label(state)}"}} {float(count)!r}'
        for state, count in counts.items()
    )
    prometheus.family(
        lines,
        "bridgeos_cloud_copy_restarts",
        "Restarts of cloud copies since each was last started on request (crash-loop signal).",
    )
    lines.append(f"bridgeos_cloud_copy_restarts {float(restarts)!r}")


def visible_templates(actor: Actor) -> QuerySet[SkillTemplate]:
    """Return the cloud's catalog and the templates of the organizations a request reaches."""
    ids = actor.organization_ids()
    templates = SkillTemplate.objects.select_related("organization")
    return templates if ids is None else templates.filter(Q(organization=None) | Q(organization_id__in=ids))
