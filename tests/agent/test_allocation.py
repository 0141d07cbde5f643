"""Test Algorithm 1: deploy, replace, run in the cloud or refuse a requested component."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import replace
from typing import Any, get_args

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridgeos_agent.allocation import (
    ActiveLocation,
    AllocationSettings,
    AllocationState,
    Cloud,
    ComponentSnapshot,
    Deploy,
    Location,
    Measurement,
    Refuse,
    Replace,
    allocate,
    allocation_state,
    link_groups,
)
from bridgeos_agent.heuristics import GIB, HEURISTICS, ZERO, Resources, Swap, Weights
from bridgeos_agent.robotconfig import Heuristic, RobotConfig, RobotResources
from bridgeos_agent.skillconfig import load_sample_skill_config


def running(usage: Resources, location: Location = "either", **more: Any) -> ComponentSnapshot:
    """A component running on the robot and using what it requires."""
    return ComponentSnapshot(location, "robot", usage, usage, **more)


def stopped(required: Resources, location: Location = "either", **more: Any) -> ComponentSnapshot:
    """A component running nowhere yet."""
    return ComponentSnapshot(location, None, required, **more)


# A robot with 8 cores, no GPU, 8192 MiB, 100 Mbit/s and 100 MB/s, of which
# 0.5 cores, 512 MiB, 60 Mbit/s and 50 MB/s are free.
TOTAL = Resources(cpu=8, gpu=0, ram=8192, bandwidth=100, io=100)
FREE = Resources(cpu=0.5, gpu=0, ram=512, bandwidth=60, io=50)
DETECTOR = Resources(cpu=2, ram=1024, bandwidth=20, io=10)


def robot(**skills: Mapping[str, ComponentSnapshot]) -> AllocationState:
    """The robot of these tests running a navigation and a vision Skill (plus any given)."""
    base: dict[str, Mapping[str, ComponentSnapshot]] = {
        "nav": {
            "mapper": running(Resources(cpu=2.5, ram=1536, bandwidth=10, io=10)),
            "planner": running(Resources(cpu=3.5, ram=2560, bandwidth=10, io=10)),
        },
        "vision": {
            "camera": running(Resources(cpu=0.5, ram=256, bandwidth=10, io=2), "robot"),
            "detector": stopped(DETECTOR),
            "lidar": stopped(DETECTOR, "robot"),
            "uploader": ComponentSnapshot("cloud", "cloud", Resources(cpu=1)),
        },
    }
    base.update(skills)
    return AllocationState(TOTAL, FREE, base)


# --------------------------------------------------------------------------- the four outcomes


def test_a_component_that_fits_the_free_resources_is_deployed() -> None:
    state = replace(robot(), free=FREE + Resources(cpu=4, ram=2048))
    # needs 2 cores, 1024 MiB, 20 Mbit/s, 10 MB/s; 4.5, 2560, 60 and 50 are free.
    assert allocate(state, "vision", "detector") == Deploy("fits the free resources")


def test_a_component_that_exactly_fits_is_deployed() -> None:
    state = replace(robot(), free=DETECTOR)
    assert isinstance(allocate(state, "vision", "detector"), Deploy)


def test_a_short_robot_replaces_the_cheapest_movable_component() -> None:
    decision = allocate(robot(), "vision", "detector")
    # Short of cpu (2 > 0.5) and ram (1024 > 512). Resource usage of each swap:
    #   mapper frees 2.5 cores and 1536 MiB: available 3, 0, 2048, 70, 60
    #     cpu (3 - 2)/8 = 0.125, ram (2048 - 1024)/8192 = 0.125,
    #     bandwidth (70 - 20)/100 = 0.5, io (60 - 10)/100 = 0.5, no GPU to count
    #     (0.125 * 0.125 * 0.5 * 0.5) ** (1/4) = (2 ** -8) ** (1/4) = 0.25
    #   planner frees 3.5 cores and 2560 MiB: available 4, 0, 3072, 70, 60
    #     (0.25 * 0.25 * 0.5 * 0.5) ** (1/4) = 0.354
    # 0.25 is the cheaper and within the default threshold 0.5.
    assert isinstance(decision, Replace)
    assert (decision.skill_id, decision.component_id, decision.links) == ("nav", "mapper", ())
    assert decision.cost == 0.25
    assert "cpu, ram" in decision.reason


def test_a_replacement_costing_exactly_the_threshold_is_taken() -> None:
    decision = allocate(robot(), "vision", "detector", AllocationSettings(threshold=0.25))
    assert isinstance(decision, Replace)
    assert decision.cost == 0.25


def test_a_replacement_above_the_threshold_sends_a_movable_component_to_the_cloud() -> None:
    decision = allocate(robot(), "vision", "detector", AllocationSettings(threshold=math.nextafter(0.25, 0)))
    assert isinstance(decision, Cloud)
    assert "nav/mapper costs 0.25" in decision.reason


def test_a_replacement_above_the_threshold_refuses_a_robot_only_component() -> None:
    decision = allocate(robot(), "vision", "lidar", AllocationSettings(threshold=0.2))
    assert isinstance(decision, Refuse)
    assert "must run on the robot" in decision.reason


def test_without_a_feasible_replacement_a_movable_component_goes_to_the_cloud() -> None:
    state = replace(robot(), free=ZERO)
    # With nothing free, mapper and planner each free enough cores and memory,
    # but only 10 of the 20 Mbit/s the detector needs.
    decision = allocate(state, "vision", "detector", AllocationSettings(threshold=math.inf))
    assert decision == Cloud(
        "short of cpu, ram, bandwidth, io and no running movable component frees enough; it may run in the cloud"
    )


def test_without_a_feasible_replacement_a_robot_only_component_is_refused() -> None:
    decision = allocate(replace(robot(), free=ZERO), "vision", "lidar", AllocationSettings(threshold=math.inf))
    assert isinstance(decision, Refuse)
    assert "no running movable component frees enough" in decision.reason


def test_a_robot_with_no_movable_component_refuses() -> None:
    state = AllocationState(TOTAL, FREE, {"vision": robot().skills["vision"]})
    assert isinstance(allocate(state, "vision", "lidar"), Refuse)


# --------------------------------------------------------------------------- preconditions


def test_a_cloud_only_component_is_not_for_the_robot_to_allocate() -> None:
    with pytest.raises(ValueError, match="'uploader' of skill 'vision' must run in the cloud"):
        allocate(robot(), "vision", "uploader")


@pytest.mark.parametrize(("skill", "component"), [("vision", "nope"), ("nope", "detector")])
def test_an_unknown_component_is_a_clear_error(skill: str, component: str) -> None:
    with pytest.raises(ValueError, match=f"no component '{component}' in skill '{skill}'"):
        allocate(robot(), skill, component)


def test_an_unknown_heuristic_is_refused_with_the_choices() -> None:
    with pytest.raises(ValueError, match="unknown heuristic 'cheapest'; choose one of resource_usage"):
        AllocationSettings(heuristic="cheapest")


def test_settings_come_from_the_robot_configuration() -> None:
    config = RobotConfig.model_validate(
        {
            "heuristic": "weighted_cost",
            "threshold": 3,
            "weights": {"gain": 2, "cost": 3, "loss": 4, "time": 5},
            "costs": {"per_gb": 0.7},
        }
    )
    assert AllocationSettings.from_config(config) == AllocationSettings("weighted_cost", 3.0, Weights(2, 3, 4, 5), 0.7)


# --------------------------------------------------------------------------- links


def test_link_groups_close_links_both_ways_and_transitively() -> None:
    components = {
        "a": stopped(ZERO, links=("b",)),
        "b": stopped(ZERO),
        "c": stopped(ZERO, links=("b",)),
        "d": stopped(ZERO),
        "e": stopped(ZERO, links=("ghost",)),
    }
    groups = link_groups(components)
    assert groups["a"] == groups["b"] == groups["c"] == ("a", "b", "c")
    assert groups["d"] == ("d",)
    assert groups["e"] == ("e",)


def test_the_requested_component_brings_its_links_requirements() -> None:
    state = robot(
        tracking={
            "detector": stopped(DETECTOR),
            "tracker": stopped(Resources(cpu=1, ram=512), links=("detector",)),
        }
    )
    state = replace(state, free=DETECTOR + Resources(bandwidth=40, io=40))
    # Alone the detector fits; with its tracker it needs 3 cores and 1536 MiB.
    decision = allocate(state, "tracking", "detector", AllocationSettings(threshold=math.inf))
    assert isinstance(decision, Replace)
    assert "short of cpu, ram" in decision.reason


def test_a_link_already_on_the_robot_is_not_counted_twice() -> None:
    state = robot(
        tracking={
            "detector": stopped(DETECTOR),
            "tracker": running(Resources(cpu=1, ram=512), links=("detector",)),
        }
    )
    state = replace(state, free=DETECTOR)
    assert isinstance(allocate(state, "tracking", "detector"), Deploy)


def test_a_component_linked_to_the_requested_one_is_never_the_replacement() -> None:
    # Moving the tracker would free exactly the missing 1.5 cores (cost 0, the best
    # possible), but it must stay with the detector.
    state = robot(
        tracking={
            "detector": stopped(DETECTOR),
            "tracker": running(Resources(cpu=1.5, ram=512), links=("detector",)),
        }
    )
    decision = allocate(state, "tracking", "detector")
    assert isinstance(decision, Replace)
    assert (decision.skill_id, decision.component_id) == ("nav", "mapper")


def test_a_replacement_takes_its_links_along_and_frees_their_usage() -> None:
    # Alone neither half frees 2 cores; together they free 2.5.
    state = robot(
        nav={
            "mapper": running(Resources(cpu=1.25, ram=768, bandwidth=5, io=5)),
            "localizer": running(Resources(cpu=1.25, ram=768, bandwidth=5, io=5), links=("mapper",)),
        }
    )
    decision = allocate(state, "vision", "detector")
    # Available 0.5 + 2.5 cores, 512 + 1536 MiB, 70 Mbit/s, 60 MB/s: the same 0.25 as mapper alone above.
    assert isinstance(decision, Replace)
    assert (decision.skill_id, decision.component_id, decision.links) == ("nav", "mapper", ("localizer",))
    assert decision.cost == 0.25


def test_a_movable_component_linked_to_a_robot_only_one_is_not_movable() -> None:
    state = robot(
        nav={
            "mapper": running(Resources(cpu=2.5, ram=1536, bandwidth=10, io=10), links=("base",)),
            "base": running(ZERO, "robot"),
        }
    )
    decision = allocate(state, "vision", "detector", AllocationSettings(threshold=math.inf))
    assert isinstance(decision, Cloud)


def test_only_components_running_on_the_robot_are_candidates() -> None:
    state = robot(
        nav={
            "mapper": replace(running(Resources(cpu=2.5, ram=1536, bandwidth=10, io=10)), active_location="cloud"),
            "planner": stopped(Resources(cpu=3.5, ram=2560, bandwidth=10, io=10)),
        }
    )
    decision = allocate(state, "vision", "detector", AllocationSettings(threshold=math.inf))
    assert isinstance(decision, Cloud)


def test_equal_costs_keep_the_first_candidate() -> None:
    twin = Resources(cpu=2.5, ram=1536, bandwidth=10, io=10)
    state = robot(nav={"first": running(twin), "second": running(twin)})
    decision = allocate(state, "vision", "detector")
    assert isinstance(decision, Replace)
    assert decision.component_id == "first"


# --------------------------------------------------------------------------- every heuristic


def test_migration_cost_prefers_the_replacement_with_less_state() -> None:
    state = robot(
        nav={
            "mapper": running(Resources(cpu=2.5, ram=1536, bandwidth=10, io=10), volume_bytes=GIB),
            "planner": running(Resources(cpu=3.5, ram=2560, bandwidth=10, io=10), ros_bytes=GIB / 4),
        }
    )
    decision = allocate(state, "vision", "detector", AllocationSettings("migration_cost", per_gb=0.1))
    # mapper: 1 GiB * 0.1 = 0.1; planner: 0.25 GiB * 0.1 = 0.025.
    assert isinstance(decision, Replace)
    assert decision.component_id == "planner"
    assert decision.cost == pytest.approx(0.025)


@pytest.mark.parametrize("heuristic", get_args(Heuristic))
def test_every_heuristic_prices_the_chosen_swap(heuristic: str) -> None:
    state = robot(
        nav={
            "mapper": running(
                Resources(cpu=2.5, ram=1536, bandwidth=10, io=10),
                local_bandwidth=6,
                cloud_bandwidth=2,
                volume_bytes=GIB / 2,
            ),
            "planner": running(
                Resources(cpu=3.5, ram=2560, bandwidth=10, io=10), local_bandwidth=1, cloud_bandwidth=3, ros_bytes=GIB
            ),
        }
    )
    decision = allocate(state, "vision", "detector", AllocationSettings(heuristic, threshold=math.inf))
    assert isinstance(decision, Replace)
    usage = state.skills["nav"][decision.component_id].usage
    expected = HEURISTICS[heuristic](
        Swap(DETECTOR, FREE + usage, TOTAL, FREE, [state.skills["nav"][decision.component_id]])
    )
    assert decision.cost == pytest.approx(expected)


# --------------------------------------------------------------------------- the snapshot


def test_the_snapshot_is_built_from_skill_configs_and_measurements() -> None:
    skill = load_sample_skill_config()
    measured = Resources(cpu=0.25, ram=200, bandwidth=15)
    state = allocation_state(
        RobotResources(cpu=2, ram=2048, bandwidth=100, io=100),
        Resources(cpu=0.5, ram=512, bandwidth=40, io=90),
        [skill],
        {("people-detection", "pointcloud"): "robot", ("people-detection", "sampler"): "robot"},
        {("people-detection", "sampler"): Measurement(measured, local_bandwidth=20, volume_bytes=1000)},
    )
    components = state.skills["people-detection"]
    assert state.total == Resources(2, 0, 2048, 100, 100)
    # pointcloud was not measured yet: it is assumed to use what it requires.
    assert components["pointcloud"] == ComponentSnapshot(
        "robot", "robot", Resources(0.3, 0, 128, 40, 2), Resources(0.3, 0, 128, 40, 2)
    )
    assert components["sampler"].usage == measured
    assert (components["sampler"].local_bandwidth, components["sampler"].volume_bytes) == (20, 1000)
    assert components["detector"] == ComponentSnapshot("either", None, Resources(1.5, 0, 768, 10, 1))
    # The detector needs 1.5 cores with 0.5 free; moving the sampler frees 0.25 more: not enough.
    decision = allocate(state, "people-detection", "detector", AllocationSettings(threshold=math.inf))
    assert isinstance(decision, Cloud)


def test_a_cloud_component_in_the_snapshot_uses_none_of_the_robot() -> None:
    skill = load_sample_skill_config()
    state = allocation_state(
        RobotResources(),
        ZERO,
        [skill],
        {("people-detection", "detector"): "cloud"},
        {("people-detection", "detector"): Measurement(Resources(cpu=1))},
    )
    assert state.skills["people-detection"]["detector"].usage == ZERO


# --------------------------------------------------------------------------- properties


def resources(most: int, often_none: bool = False) -> st.SearchStrategy[Resources]:
    """Whole amounts up to most of each kind, so sums are exact and fits is unambiguous."""
    amount = st.integers(min_value=0, max_value=most).map(float)
    if often_none:
        amount = st.one_of(st.just(0.0), amount)
    return st.builds(Resources, amount, amount, amount, amount, amount)


amounts = st.integers(min_value=0, max_value=8).map(float)
# Weighted towards movable components running on the robot, so replacements are common.
LOCATIONS: list[Location] = ["either", "either", "either", "robot", "cloud"]
PLACES: dict[Location, list[ActiveLocation]] = {
    "robot": ["robot", None],
    "cloud": ["cloud", None],
    "either": ["robot", "robot", "cloud", None],
}


@st.composite
def skills(draw: st.DrawFn, name: str) -> dict[str, ComponentSnapshot]:
    """A Skill of one to four components with random links, placements and measurements."""
    ids = [f"{name}{i}" for i in range(draw(st.integers(1, 4)))]
    components = {}
    for index, cid in enumerate(ids):
        required_location = draw(st.sampled_from(LOCATIONS))
        components[cid] = ComponentSnapshot(
            required_location=required_location,
            active_location=draw(st.sampled_from(PLACES[required_location])),
            required=draw(resources(3, often_none=True)),
            usage=draw(resources(8)),
            links=tuple(draw(st.lists(st.sampled_from(ids[:index]), unique=True)) if index else ()),
            local_bandwidth=draw(amounts),
            cloud_bandwidth=draw(amounts),
            volume_bytes=draw(st.integers(0, 2 * GIB)),
            ros_bytes=draw(st.integers(0, 2 * GIB)),
        )
    return components


Request = tuple[AllocationState, str, str, AllocationSettings]


@st.composite
def requests(draw: st.DrawFn) -> Request:
    """A robot snapshot, a component it is asked to run and the user's settings."""
    names = ["s", "t", "u"][: draw(st.integers(1, 3))]
    snapshot = {name: draw(skills(name)) for name in names}
    candidates = [(s, c) for s in names for c, comp in snapshot[s].items() if comp.required_location != "cloud"]
    if not candidates:
        snapshot["s"]["s0"] = replace(snapshot["s"]["s0"], required_location="either")
        candidates = [("s", "s0")]
    skill_id, component_id = draw(st.sampled_from(candidates))
    if draw(st.booleans()):
        # A big movable component that frees enough for any request, so replacements compete.
        big = draw(st.builds(Resources, *[st.integers(12, 20).map(float)] * 5))
        snapshot["v"] = {"v0": ComponentSnapshot("either", "robot", big, big, ros_bytes=draw(st.integers(0, 2 * GIB)))}
    choice = AllocationSettings(
        draw(st.sampled_from(sorted(HEURISTICS))),
        draw(st.sampled_from([0.0, 0.25, 0.5, 1.0, 10.0, math.inf, math.inf])),
        draw(st.builds(Weights, amounts, amounts, amounts, amounts)),
        draw(st.sampled_from([0.0, 0.1])),
    )
    state = AllocationState(draw(resources(16)), draw(resources(4, often_none=True)), snapshot)
    return state, skill_id, component_id, choice


def closure(components: Mapping[str, ComponentSnapshot], start: str) -> set[str]:
    """Everything reachable from start over links followed both ways."""
    seen, todo = {start}, [start]
    while todo:
        here = todo.pop()
        for cid, component in components.items():
            if (cid in components[here].links or here in component.links) and cid not in seen:
                seen.add(cid)
                todo.append(cid)
    return seen


def needed(state: AllocationState, skill_id: str, component_id: str) -> Resources:
    """What the requested component and its links still need on the robot."""
    components = state.skills[skill_id]
    total = ZERO
    for cid in closure(components, component_id):
        if components[cid].active_location != "robot":
            total += components[cid].required
    return total


def feasible_costs(
    state: AllocationState, skill_id: str, component_id: str, choice: AllocationSettings
) -> dict[tuple[str, str], float]:
    """Price every legal replacement that frees enough, keyed by (skill, component)."""
    requirement = needed(state, skill_id, component_id)
    linked = closure(state.skills[skill_id], component_id)
    costs: dict[tuple[str, str], float] = {}
    for sid, components in state.skills.items():
        for cid, component in components.items():
            if component.active_location != "robot" or component.required_location != "either":
                continue
            if sid == skill_id and cid in linked:
                continue
            group = [g for g in components if g in closure(components, cid)]
            if any(components[g].required_location != "either" for g in group):
                continue
            moving = [components[g] for g in group if components[g].active_location == "robot"]
            available = state.free
            for member in moving:
                available += member.usage
            if requirement.fits(available):
                costs[sid, cid] = HEURISTICS[choice.heuristic](
                    Swap(requirement, available, state.total, state.free, moving, choice.per_gb, choice.weights)
                )
    return costs


@settings(max_examples=250, deadline=None)
@given(requests())
def test_deploy_exactly_when_the_requirement_fits_the_free_resources(request: Request) -> None:
    state, skill_id, component_id, choice = request
    decision = allocate(state, skill_id, component_id, choice)
    assert isinstance(decision, Deploy) == needed(state, skill_id, component_id).fits(state.free)


@settings(max_examples=250, deadline=None)
@given(requests())
def test_a_replacement_is_legal_frees_enough_and_costs_least(request: Request) -> None:
    state, skill_id, component_id, choice = request
    decision = allocate(state, skill_id, component_id, choice)
    if not isinstance(decision, Replace):
        return
    components = state.skills[decision.skill_id]
    chosen = components[decision.component_id]
    group = closure(components, decision.component_id)
    # Never linked to the request, never pinned, always running on the robot.
    assert chosen.active_location == "robot"
    assert all(components[g].required_location == "either" for g in group)
    assert not (decision.skill_id == skill_id and component_id in group)
    assert set(decision.links) == {g for g in group if components[g].active_location == "robot"} - {
        decision.component_id
    }
    # It frees enough.
    available = state.free
    for g in group:
        if components[g].active_location == "robot":
            available += components[g].usage
    assert needed(state, skill_id, component_id).fits(available)
    # It is the cheapest and within the threshold.
    costs = feasible_costs(state, skill_id, component_id, choice)
    assert decision.cost == pytest.approx(costs[decision.skill_id, decision.component_id])
    assert decision.cost == pytest.approx(min(costs.values()))
    assert decision.cost <= choice.threshold


@settings(max_examples=250, deadline=None)
@given(requests())
def test_cloud_or_refuse_only_when_no_replacement_is_cheap_enough(request: Request) -> None:
    state, skill_id, component_id, choice = request
    decision = allocate(state, skill_id, component_id, choice)
    if not isinstance(decision, Cloud | Refuse):
        return
    assert not needed(state, skill_id, component_id).fits(state.free)
    # An infinite cost never wins, even against an infinite threshold (the thesis starts minCost at infinity).
    costs = feasible_costs(state, skill_id, component_id, choice).values()
    assert all(cost == math.inf or cost > choice.threshold for cost in costs)
    assert isinstance(decision, Cloud) == (state.skills[skill_id][component_id].required_location == "either")
