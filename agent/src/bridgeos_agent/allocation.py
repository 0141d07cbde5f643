"""Decide whether a requested component may run on the robot (thesis Algorithm 1).

Pure: ``allocate`` reads a frozen snapshot of the robot and returns one of four
decisions. ``allocation_state`` builds that snapshot from Skill configurations and the
controller's measurements, so the controller's glue stays one call each.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Literal

from bridgeos_agent.heuristics import HEURISTICS, ZERO, Resources, Swap, Weights

if TYPE_CHECKING:
    from bridgeos_agent.robotconfig import RobotConfig
    from bridgeos_agent.skillconfig import SkillConfig

__all__ = [
    "ActiveLocation",
    "AllocationDecision",
    "AllocationSettings",
    "AllocationState",
    "Cloud",
    "ComponentSnapshot",
    "Deploy",
    "Location",
    "Measurement",
    "Refuse",
    "Replace",
    "Resources",
    "allocate",
    "allocation_state",
    "link_groups",
]

Location = Literal["robot", "cloud", "either"]
ActiveLocation = Literal["robot", "cloud"] | None


@dataclass(frozen=True, slots=True)
class ComponentSnapshot:
    """Snapshot one component as the allocator sees it."""

    required_location: Location  # from the Skill configuration
    active_location: ActiveLocation  # where it runs now; None when it runs nowhere
    required: Resources  # what the configuration says it needs
    usage: Resources = ZERO  # what it was measured to use on the robot
    links: tuple[str, ...] = ()  # ids of components of the same Skill it must share a location with
    local_bandwidth: float = 0.0  # Mbit/s it exchanges with components on the robot
    cloud_bandwidth: float = 0.0  # Mbit/s it exchanges with components in the cloud
    volume_bytes: float = 0.0  # Docker volume state a migration must copy
    ros_bytes: float = 0.0  # stored ROS messages a migration must replay


@dataclass(frozen=True, slots=True)
class AllocationState:
    """Snapshot the robot: its capacity, what is free now and each active Skill's components."""

    total: Resources
    free: Resources
    skills: Mapping[str, Mapping[str, ComponentSnapshot]]  # skill id -> component id -> state


@dataclass(frozen=True, slots=True)
class AllocationSettings:
    """Hold the user's choices for Algorithm 1: heuristic, threshold, weights and price."""

    heuristic: str = "resource_usage"
    threshold: float = 0.5
    weights: Weights = field(default_factory=Weights)
    per_gb: float = 0.1

    def __post_init__(self) -> None:
        if self.heuristic not in HEURISTICS:
            raise ValueError(f"unknown heuristic {self.heuristic!r}; choose one of {', '.join(HEURISTICS)}")

    @classmethod
    def from_config(cls, config: RobotConfig) -> AllocationSettings:
        """Read the allocation choices from a robot configuration."""
        return cls(config.heuristic, config.threshold, Weights.of(config.weights), config.costs.per_gb)


@dataclass(frozen=True, slots=True)
class Deploy:
    """Deploy the component on the robot: it fits the free resources."""

    reason: str


@dataclass(frozen=True, slots=True)
class Replace:
    """Migrate a running component and its links to the cloud first, then deploy."""

    skill_id: str
    component_id: str
    links: tuple[str, ...]  # the replacement's linked components, which migrate with it
    cost: float
    reason: str


@dataclass(frozen=True, slots=True)
class Cloud:
    """Run the component in the cloud instead: the robot has no room and it may run there."""

    reason: str


@dataclass(frozen=True, slots=True)
class Refuse:
    """Do not deploy: the robot has no room and the component must run on the robot."""

    reason: str


AllocationDecision = Deploy | Replace | Cloud | Refuse


@dataclass(frozen=True, slots=True)
class Measurement:
    """Hold what the controller measured about one component at run time."""

    usage: Resources | None = None  # None: assume it uses what its configuration requires
    local_bandwidth: float = 0.0
    cloud_bandwidth: float = 0.0
    volume_bytes: float = 0.0
    ros_bytes: float = 0.0


def link_groups(components: Mapping[str, ComponentSnapshot]) -> dict[str, tuple[str, ...]]:
    """Map each component of a Skill to its link group: itself and everything linked, transitively."""
    # Links are symmetric and transitive: A-B and B-C put A, B and C in one location.
    parent = {cid: cid for cid in components}

    def root(cid: str) -> str:
        while parent[cid] != cid:
            parent[cid] = parent[parent[cid]]
            cid = parent[cid]
        return cid

    for cid, component in components.items():
        for other in component.links:
            if other in parent:  # a dangling link names nothing to move; SkillConfig rejects it anyway
                parent[root(cid)] = root(other)
    members: dict[str, list[str]] = {}
    for cid in components:
        members.setdefault(root(cid), []).append(cid)
    return {cid: tuple(members[root(cid)]) for cid in components}


def _cheapest_replacement(
    state: AllocationState,
    skill_id: str,
    linked: tuple[str, ...],
    resources: Resources,
    settings: AllocationSettings,
) -> tuple[tuple[str, str, tuple[str, ...]] | None, float]:
    """Find the running movable component whose move frees enough at the lowest cost (lines 10-36)."""
    heuristic = HEURISTICS[settings.heuristic]
    replacement: tuple[str, str, tuple[str, ...]] | None = None
    min_cost = math.inf
    for sid, skill in state.skills.items():
        groups = link_groups(skill)
        seen: set[str] = set()
        for cid, candidate in skill.items():
            if cid in seen or candidate.active_location != "robot" or candidate.required_location != "either":
                continue
            if sid == skill_id and cid in linked:
                continue
            group = groups[cid]
            seen.update(group)
            members = [skill[m] for m in group]
            # A movable component linked to a robot-only one can never leave (the thesis
            # assumes links of a movable component are movable too).
            if any(member.required_location != "either" for member in members):
                continue
            # Every member of a group is evaluated as one swap, whichever is the base, so
            # the heuristic runs once per group and its cost never depends on the base.
            moving_ids = [m for m in group if skill[m].active_location == "robot"]
            moving = [skill[m] for m in moving_ids]
            available = state.free
            for member in moving:
                available += member.usage
            if not resources.fits(available):
                continue
            cost = heuristic(
                Swap(resources, available, state.total, state.free, moving, settings.per_gb, settings.weights)
            )
            if cost < min_cost:  # strict, as in the thesis: the first of equal costs wins, inf never does
                replacement = (sid, cid, tuple(m for m in moving_ids if m != cid))
                min_cost = cost
    return replacement, min_cost


def allocate(
    state: AllocationState,
    skill_id: str,
    component_id: str,
    settings: AllocationSettings | None = None,
) -> AllocationDecision:
    """Decide whether a component runs on the robot, after a replacement, in the cloud, or not at all."""
    settings = settings or AllocationSettings()
    try:
        components = state.skills[skill_id]
        requested = components[component_id]
    except KeyError:
        raise ValueError(f"no component {component_id!r} in skill {skill_id!r}") from None
    if requested.required_location == "cloud":
        raise ValueError(
            f"component {component_id!r} of skill {skill_id!r} must run in the cloud; "
            "only 'robot' and 'either' components are allocated on the robot"
        )

    linked = link_groups(components)[component_id]
    # Members already on the robot hold their resources already; counting them again
    # would refuse a component whose link is running (the thesis counts every link).
    resources = ZERO
    for cid in linked:
        if components[cid].active_location != "robot":
            resources += components[cid].required

    # Line 7 of the thesis compares with robotResources but means the free resources of line 1.
    if resources.fits(state.free):
        return Deploy("fits the free resources")

    replacement, min_cost = _cheapest_replacement(state, skill_id, linked, resources, settings)
    short = ", ".join(resources.short_of(state.free))
    if replacement is not None and min_cost <= settings.threshold:
        sid, cid, links = replacement
        return Replace(
            sid,
            cid,
            links,
            min_cost,
            f"short of {short}; moving {sid}/{cid} to the cloud frees enough at "
            f"{settings.heuristic} cost {min_cost:.4g} <= threshold {settings.threshold:g}",
        )
    if replacement is None:
        why = f"short of {short} and no running movable component frees enough"
    else:
        sid, cid, _ = replacement
        why = (
            f"short of {short}; the cheapest replacement {sid}/{cid} costs {min_cost:.4g} "
            f"> threshold {settings.threshold:g}"
        )
    if requested.required_location == "either":
        return Cloud(f"{why}; it may run in the cloud")
    return Refuse(f"{why}; it must run on the robot")


def allocation_state(
    total: Any,
    free: Resources,
    skills: Iterable[SkillConfig],
    active_locations: Mapping[tuple[str, str], ActiveLocation],
    measurements: Mapping[tuple[str, str], Measurement] | None = None,
) -> AllocationState:
    """Build the allocator's snapshot from Skill configurations and run-time measurements.

    ``total`` is the robot's capacity (``RobotResources`` or ``Resources``); ``skills`` are
    the active Skills plus the one asking; ``active_locations`` and ``measurements`` are
    keyed by ``(skill_id, component_id)``, and a component missing from them runs nowhere.
    """
    measurements = measurements or {}
    snapshot: dict[str, dict[str, ComponentSnapshot]] = {}
    for skill in skills:
        components: dict[str, ComponentSnapshot] = {}
        for cid, config in skill.components.items():
            key = (skill.skill_id, cid)
            active = active_locations.get(key)
            required = Resources.of(config.resources)
            measured = measurements.get(key, Measurement())
            if active != "robot":
                usage = ZERO  # it uses nothing of the robot's
            elif measured.usage is None:
                usage = required  # not measured yet: trust the configuration
            else:
                usage = measured.usage
            components[cid] = ComponentSnapshot(
                required_location=config.location,
                active_location=active,
                required=required,
                usage=usage,
                links=tuple(config.links),
                local_bandwidth=measured.local_bandwidth,
                cloud_bandwidth=measured.cloud_bandwidth,
                volume_bytes=measured.volume_bytes,
                ros_bytes=measured.ros_bytes,
            )
        snapshot[skill.skill_id] = components
    return AllocationState(Resources.of(total), free, snapshot)
