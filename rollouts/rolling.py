"""Domain actions on rollouts: make one (its group fixed or followed, its batches planned), pause, resume, abort."""

from __future__ import annotations

from datetime import timedelta
from typing import Any

from django.contrib.auth.models import AbstractBaseUser
from django.core.exceptions import ValidationError
from django.db import connection, transaction
from django.db.models import Count, QuerySet
from django.utils import timezone

from bridgeos_agent.protocol import MAX_HOLD_S, Event, SkillStatusName
from monitoring import prometheus
from monitoring.choices import Level
from monitoring.services import record_event
from robots.access import Actor
from robots.labels import parse_selector, selector_q
from robots.models import Robot
from robots.services import push_to_robot
from skills.models import Skill

from .executor import lock_key
from .gates import parse_conditions, parse_share
from .models import Release, Rollout, RolloutRobot, UpdateHold
from .strategy import parse_strategy

GATE_KEYS = ("conditions", "router_dropped_max")
ACTIVE = (Rollout.State.RUNNING, Rollout.State.PAUSED, Rollout.State.ROLLING_BACK)


class Conflict(Exception):
    """The request clashes with the state it would change (a rollout already moving the same robots)."""


def parse_gates(data: Any) -> dict[str, Any]:
    """Read a rollout's gates (``{"conditions": [...]}``); ValidationError naming the bad field."""
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValidationError({"gates": ['The gates are a JSON object: {"conditions": ["cpu < 0.8"]}.']})
    unknown = sorted(set(data) - set(GATE_KEYS))
    if unknown:
        raise ValidationError({f"gates.{unknown[0]}": [f"Unknown; gates have {', '.join(GATE_KEYS)}."]})
    conditions = parse_conditions(data.get("conditions"))
    gates: dict[str, Any] = {"conditions": [str(condition) for condition in conditions]} if conditions else {}
    if data.get("router_dropped_max") is not None:
        gates["router_dropped_max"] = parse_share(data["router_dropped_max"], "gates.router_dropped_max")
    return gates


def create_rollout(
    release: Release,
    selector: str,
    *,
    follow: bool = False,
    strategy: Any = None,
    gates: Any = None,
    user: AbstractBaseUser | None = None,
) -> Rollout:
    """Start a release on the robots of its organization that a selector names, in planned batches; all or nothing."""
    parsed_selector = parse_selector(selector)
    plan = parse_strategy(strategy)
    stored_gates = parse_gates(gates)
    with transaction.atomic():
        robots = list(
            Robot.objects.select_for_update(no_key=True)
            .filter(organization_id=release.organization_id)
            .filter(selector_q(parsed_selector))
            .order_by("id")
            .values_list("id", flat=True)
        )
        if not robots and not follow:
            raise ValidationError({"selector": [f"{selector!r} matches none of the organization's robots."]})
        busy = (
            RolloutRobot.objects.filter(
                robot_id__in=robots,
                rollout__release__skill_id=release.skill_id,
                rollout__state__in=ACTIVE,
            )
            .values_list("robot_id", "rollout_id")
            .first()
        )
        if busy is not None:
            raise Conflict(
                f"Robot {busy[0]} is in rollout {busy[1]} of {release.skill_id}, which is still active: "
                "wait for it, or abort it first."
            )
        sizes = plan.batches(len(robots)) or [0]
        rollout = Rollout.objects.create(
            organization_id=release.organization_id,
            release=release,
            selector=str(parsed_selector),
            follow=follow,
            strategy=strategy or {},
            gates=stored_gates,
            batch_sizes=sizes,
            batch_started_at=timezone.now(),
            created_by=user,
            created_by_name=user.get_username() if user is not None else "",
        )
        members, start = [], 0
        for batch, size in enumerate(sizes):
            members += [
                RolloutRobot(rollout=rollout, robot_id=robot_id, batch=batch)
                for robot_id in robots[start : start + size]
            ]
            start += size
        RolloutRobot.objects.bulk_create(members, batch_size=1000)
        record_event(
            f"Rollout {rollout.id} of {release.skill_id} #{release.number} to {len(robots)} robots "
            f"({parsed_selector}{', following' if follow else ''}) in {len(sizes)} batches",
            kind="rollout",
            skill=release.skill_id,
            data={"rollout": rollout.id, "release": release.number, "state": rollout.state},
            organization_id=release.organization_id,
        )
        _prefetch_on_commit(release, robots)
    return rollout


def _prefetch_on_commit(release: Release, robots: list[str]) -> None:
    """Send the release to the group's robots running the Skill, so each fetches its images before its batch.

    A running Skill keeps its config on the robot until it is restarted (the agent only fetches the
    images), so nothing changes on a robot the rollout never reaches.
    """
    if not release.robot_images:
        return  # nothing to download
    running = list(
        Skill.objects.filter(
            robot_id__in=robots,
            robot__connected=True,
            skill_id=release.skill_id,
            status__in=[SkillStatusName.RUNNING, SkillStatusName.STARTING],
        ).values_list("robot_id", flat=True)
    )
    data = {"skill": release.skill_id, "config": release.config}
    transaction.on_commit(lambda: [push_to_robot(robot_id, Event.SKILL_CONFIG, data) for robot_id in running])


def steer(rollout: Rollout, action: str, who: str) -> Rollout:
    """Pause, resume or abort a rollout; Conflict when its state does not allow it."""
    with transaction.atomic():
        if connection.vendor == "postgresql":
            # Wait for a step the executor is taking on it to end (executor.holding's lock).
            with connection.cursor() as cursor:
                cursor.execute("SELECT pg_advisory_xact_lock(hashtextextended(%s, 0))", [lock_key(rollout.pk)])
        locked = Rollout.objects.select_for_update(of=("self",)).select_related("release").get(pk=rollout.pk)
        state = locked.state
        if action == "pause":
            if state != Rollout.State.RUNNING:
                raise Conflict(f"Rollout {locked.id} is {state}; only a running rollout pauses.")
            locked.state, locked.reason = Rollout.State.PAUSED, f"paused by {who}"
        elif action == "resume":
            if state != Rollout.State.PAUSED:
                raise Conflict(f"Rollout {locked.id} is {state}; only a paused rollout resumes.")
            locked.state, locked.reason = Rollout.State.RUNNING, f"resumed by {who}"
        else:
            if state not in (Rollout.State.RUNNING, Rollout.State.PAUSED):
                raise Conflict(f"Rollout {locked.id} is {state}; only a running or paused rollout is aborted.")
            # An abort puts every robot it touched back, as a failed gate does.
            locked.state, locked.reason = Rollout.State.ROLLING_BACK, f"aborted by {who}"
        locked.save(update_fields=["state", "reason", "updated_at"])
        record_event(
            f"Rollout {locked.id} {action}d by {who}" if action != "abort" else f"Rollout {locked.id} aborted by {who}",
            level=Level.WARNING if action == "abort" else Level.INFO,
            kind="rollout",
            skill=locked.release.skill_id,
            data={"rollout": locked.id, "release": locked.release.number, "state": locked.state},
            organization_id=locked.organization_id,
        )
    return locked


def visible_rollouts(actor: Actor) -> QuerySet[Rollout]:
    """Return the rollouts of the organizations a request reaches (staff: all)."""
    ids = actor.organization_ids()
    rollouts = Rollout.objects.select_related("release", "organization")
    return rollouts if ids is None else rollouts.filter(organization_id__in=ids)


def hold_updates(robot: Robot, holder: str, seconds: float, reason: str = "") -> UpdateHold:
    """Hold a robot's updates until released or for ``seconds`` at most (a rollout defers it meanwhile)."""
    if not 0 < seconds <= MAX_HOLD_S:
        raise ValidationError({"seconds": [f"A hold lasts more than 0 and at most {MAX_HOLD_S:g} seconds."]})
    until = timezone.now() + timedelta(seconds=seconds)
    with transaction.atomic():
        hold, _ = UpdateHold.objects.update_or_create(
            robot=robot, defaults={"holder": holder, "reason": reason, "until": until, "created_at": timezone.now()}
        )
        record_event(
            f"Updates held by {holder} until {until:%Y-%m-%d %H:%M:%S}" + (f": {reason}" if reason else ""),
            robot_id=robot.id,
            kind="update_hold",
            data={"holder": holder, "until": until.isoformat()},
        )
    return hold


def component_hold(robot_id: str, skill_id: str, component_id: str, seconds: float, reason: str) -> None:
    """Apply a component's hold (through its Components API) on its robot's updates; 0 seconds releases it."""
    robot = Robot.objects.get(id=robot_id)
    holder = f"component {skill_id}/{component_id}"
    if seconds > 0:
        hold_updates(robot, holder, seconds, reason)
    else:
        release_hold(robot, holder)


def release_hold(robot: Robot, holder: str) -> bool:
    """Release a robot's update hold; return whether there was one."""
    with transaction.atomic():
        deleted, _ = UpdateHold.objects.filter(robot=robot).delete()
        if deleted:
            record_event(f"Update hold released by {holder}", robot_id=robot.id, kind="update_hold")
    return bool(deleted)


def write_rollout_families(lines: list[str]) -> None:
    """Add rollouts by state and their robots by status to a /metrics scrape (read from PostgreSQL)."""
    states = dict.fromkeys(Rollout.State.values, 0)
    for state, count in Rollout.objects.values_list("state").annotate(n=Count("id")).order_by():
        states[state] = count
    prometheus.family(lines, "bridgeos_rollouts", "Rollouts by state.")
    lines.extend(f'bridgeos_rollouts{{state="{state}"}} {float(count)!r}' for state, count in states.items())
    # Robots of active rollouts only: a finished rollout's robots would count forever.
    statuses = dict.fromkeys(RolloutRobot.Status.values, 0)
    active = RolloutRobot.objects.filter(rollout__state__in=ACTIVE)
    for status, count in active.values_list("status").annotate(n=Count("id")).order_by():
        statuses[status] = count
    prometheus.family(lines, "bridgeos_rollout_robots", "Robots of running, paused or rolling-back rollouts by status.")
    lines.extend(f'bridgeos_rollout_robots{{status="{status}"}} {float(count)!r}' for status, count in statuses.items())
