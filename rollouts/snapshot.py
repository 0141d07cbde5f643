"""What one executor tick reads at once about a rollout's robots: their Skills, crashes and holds, and a tally."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from django.db.models import Count, Prefetch

from bridgeos_agent.protocol import ComponentStatusName, Event
from monitoring.models import Event as LogEvent
from skills.models import Component, Skill

from .models import Rollout, RolloutRobot, UpdateHold

S = RolloutRobot.Status


@dataclass
class Seen:
    """What a tick read at once about the robots it steps: their Skills, components, crashes and holds."""

    skills: dict[str, Skill] = field(default_factory=dict)
    crashes: dict[str, list[LogEvent]] = field(default_factory=dict)
    holds: dict[str, UpdateHold] = field(default_factory=dict)


def read_seen(rollout: Rollout, members: list[RolloutRobot]) -> Seen:
    """Read in three queries what the steps of ``members`` need (rather than a few queries per robot)."""
    seen = Seen()
    changing = [m for m in members if m.status in (S.DOWNLOADING, S.INSTALLING, S.VERIFYING)]
    if changing:
        # Their statuses, not their configs: a tick reads this for every robot of the batch.
        skills = (
            Skill.objects.filter(robot_id__in=[m.robot_id for m in changing], skill_id=rollout.release.skill_id)
            .only("id", "robot_id", "skill_id", "status", "updated_at")
            .prefetch_related(Prefetch("components", queryset=Component.objects.defer("resources")))
        )
        seen.skills = {skill.robot_id: skill for skill in skills}
    verifying = [m for m in members if m.status == S.VERIFYING and m.verify_from is not None]
    if verifying:
        since = min(m.verify_from for m in verifying if m.verify_from is not None)
        crashes = LogEvent.objects.filter(
            robot_id__in=[m.robot_id for m in verifying],
            skill=rollout.release.skill_id,
            kind=Event.COMPONENT_STATUS,
            ts__gte=since,
            data__status__in=[ComponentStatusName.FAILED, ComponentStatusName.STOPPED],
        ).order_by("ts")
        for crash in crashes:
            seen.crashes.setdefault(str(crash.robot_id), []).append(crash)
    waiting = [m.robot_id for m in members if m.status in (S.PENDING, S.DEFERRED)]
    if waiting:
        seen.holds = {hold.robot_id: hold for hold in UpdateHold.objects.filter(robot_id__in=waiting)}
    return seen


@dataclass
class Tally:
    """How many of a rollout's robots of the batches begun so far are in each status, by batch."""

    counts: dict[tuple[int, str], int]

    def count(self, *, batch: int | None = None, statuses: Iterable[Any] | None = None) -> int:
        wanted = None if statuses is None else set(statuses)
        return sum(
            n
            for (at, status), n in self.counts.items()
            if (batch is None or at == batch) and (wanted is None or status in wanted)
        )

    def size(self, batch: int) -> int:
        return self.count(batch=batch)


def tally(rollout: Rollout) -> Tally:
    """Count the robots of the batches begun so far by batch and status, in one query."""
    rows = (
        rollout.robots.filter(batch__lte=rollout.batch)
        .values_list("batch", "status")
        .annotate(n=Count("id"))
        .order_by()
    )
    return Tally({(batch, status): n for batch, status, n in rows})
