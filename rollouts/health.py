"""A rollout's health gate on one robot: what its new version shows during the soak, read from what the cloud stores.

A robot passes when, for its whole soak, its Skill runs, every component runs where it was
placed, no component crashed or restarted, every condition of the rollout holds over the
metrics its robot reported in the window, and its Skill Router dropped no more than the gate
allows of what it routed (the rates the robot reports of its router's statistics).
"""

from __future__ import annotations

from datetime import datetime

from bridgeos_agent.delivery import ROUTER_DELIVERED, ROUTER_DROPPED
from bridgeos_agent.protocol import ComponentStatusName, SkillStatusName
from monitoring.models import Event as LogEvent
from monitoring.models import Metric
from skills.models import Skill

from .gates import RESOURCES, ROUTER_DROPPED_MAX, parse_conditions, router_dropped_share
from .models import Rollout, RolloutRobot

UP = (ComponentStatusName.RUNNING, ComponentStatusName.MIGRATING)


def health_problem(member: RolloutRobot, skill: Skill, crashes: list[LogEvent]) -> str:
    """Say what is wrong with a robot's new version now (its components prefetched), or return an empty string."""
    if skill.status != SkillStatusName.RUNNING:
        return f"the Skill is {skill.status}"
    for component in skill.components.all():
        if component.status not in UP:
            why = f": {component.message}" if component.message else ""
            return f"component {component.component_id} is {component.status}{why}"
        if not component.active_location:
            return f"component {component.component_id} runs nowhere"
    assert member.verify_from is not None
    crash = next((crash for crash in crashes if crash.ts >= member.verify_from), None)
    if crash is not None:
        return f"component {crash.component} crashed or restarted while verified: {crash.message}"
    return ""


def failed_conditions(rollout: Rollout, member: RolloutRobot, now: datetime) -> str:
    """Check the rollout's conditions over the robot's metrics of the soak window; name those missed."""
    conditions = parse_conditions((rollout.gates or {}).get("conditions"))
    missed = []
    for condition in conditions:
        points = Metric.objects.filter(
            robot_id=member.robot_id, name=condition.metric, ts__gte=member.verify_from, ts__lte=now
        )
        if condition.metric not in RESOURCES:
            points = points.filter(skill=rollout.release.skill_id)
        values = list(points.values_list("value", flat=True))
        if not condition.holds(values):
            mean = f"mean {sum(values) / len(values):g}" if values else "no points"
            missed.append(f"{condition} ({mean} over the soak)")
    return "gate missed: " + "; ".join(missed) if missed else ""


def router_problem(rollout: Rollout, member: RolloutRobot, now: datetime) -> str:
    """Fail a robot whose Skill Router dropped more than the gate allows over the soak (its reported rates)."""
    router = rollout.release.config.get("router") or {}
    if not (router.get("topics") or router.get("services")):
        return ""
    limit = (rollout.gates or {}).get("router_dropped_max", ROUTER_DROPPED_MAX)
    points = Metric.objects.filter(
        robot_id=member.robot_id,
        skill=rollout.release.skill_id,
        name__in=[ROUTER_DELIVERED, ROUTER_DROPPED],
        ts__gte=member.verify_from,
        ts__lte=now,
    ).values_list("name", "value")
    rates: dict[str, list[float]] = {ROUTER_DELIVERED: [], ROUTER_DROPPED: []}
    for name, value in points:
        rates[name].append(value)
    share = router_dropped_share(rates[ROUTER_DELIVERED], rates[ROUTER_DROPPED])
    if share is not None and share > limit:
        return f"the Skill Router dropped {share:.1%} of its messages over the soak (the gate allows {limit:.1%})"
    return ""
