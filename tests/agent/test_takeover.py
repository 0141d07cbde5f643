"""Test the cloud role takeover decisions (thesis Algorithm 7)."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridgeos_agent.allocation import ActiveLocation, ComponentSnapshot, Location
from bridgeos_agent.heuristics import ZERO, Resources
from bridgeos_agent.takeover import CloudMonitor, plan_revert, plan_takeover


def in_cloud(required: Resources, location: Location = "either") -> ComponentSnapshot:
    """A component running in the cloud."""
    return ComponentSnapshot(location, "cloud", required)


def on_robot(required: Resources, location: Location = "either") -> ComponentSnapshot:
    """A component running on the robot."""
    return ComponentSnapshot(location, "robot", required, required)


# --------------------------------------------------------------------------- plan_takeover


def test_a_skill_whose_cloud_part_fits_is_taken_over_whole() -> None:
    skills = {
        "nav": {
            "driver": on_robot(Resources(cpu=1), "robot"),
            "mapper": in_cloud(Resources(cpu=1, ram=512)),
            "planner": in_cloud(Resources(cpu=0.5, ram=256), "robot"),
        }
    }
    # mapper + planner need 1.5 cores and 768 MiB; 2 cores and 1024 MiB are free.
    assert plan_takeover(skills, Resources(cpu=2, ram=1024)) == {"nav": ["mapper", "planner"]}


def test_a_cloud_part_that_exactly_fits_is_taken_over() -> None:
    skills = {"nav": {"mapper": in_cloud(Resources(cpu=1, ram=512))}}
    assert plan_takeover(skills, Resources(cpu=1, ram=512)) == {"nav": ["mapper"]}


def test_a_skill_is_taken_over_all_or_nothing() -> None:
    skills = {"nav": {"mapper": in_cloud(Resources(cpu=1)), "planner": in_cloud(Resources(cpu=1.5))}}
    # 2.5 cores needed, 2 free: launching only the mapper would not restore the Skill.
    assert plan_takeover(skills, Resources(cpu=2)) == {}


def test_a_skill_with_a_running_cloud_only_component_is_skipped_entirely() -> None:
    skills = {
        "vision": {
            "camera": in_cloud(Resources(cpu=0.5)),  # before the blocker: still not launched
            "trainer": in_cloud(Resources(gpu=1), "cloud"),
            "detector": in_cloud(Resources(cpu=1)),
        },
        "nav": {"mapper": in_cloud(Resources(cpu=1))},
    }
    assert plan_takeover(skills, Resources(cpu=4, gpu=1)) == {"nav": ["mapper"]}


def test_a_stopped_cloud_only_component_does_not_block_the_skill() -> None:
    skills = {
        "vision": {
            "trainer": ComponentSnapshot("cloud", None, Resources(gpu=1)),
            "detector": in_cloud(Resources(cpu=1)),
        }
    }
    assert plan_takeover(skills, Resources(cpu=4)) == {"vision": ["detector"]}


def test_components_running_nowhere_or_on_the_robot_are_left_alone() -> None:
    skills = {
        "nav": {
            "mapper": on_robot(Resources(cpu=1)),
            "planner": ComponentSnapshot("either", None, Resources(cpu=1)),
        }
    }
    assert plan_takeover(skills, Resources(cpu=4)) == {}


def test_two_skills_cannot_claim_the_same_headroom() -> None:
    skills = {
        "nav": {"mapper": in_cloud(Resources(cpu=1.5, ram=512))},
        "vision": {"detector": in_cloud(Resources(cpu=1, ram=512))},
        "speech": {"asr": in_cloud(Resources(cpu=0.5, ram=256))},
    }
    # 2 cores, 1024 MiB free. nav takes 1.5 cores and 512 MiB, leaving 0.5 and 512:
    # vision (1 core) no longer fits though it would alone; speech (0.5, 256) does.
    assert plan_takeover(skills, Resources(cpu=2, ram=1024)) == {"nav": ["mapper"], "speech": ["asr"]}


def test_nothing_to_take_over_without_skills() -> None:
    assert plan_takeover({}, Resources(cpu=4)) == {}


# --------------------------------------------------------------------------- plan_revert


def test_revert_stops_every_component_the_takeover_launched() -> None:
    migrations = {"nav": ["mapper", "planner"], "speech": ["asr"]}
    assert plan_revert(migrations) == [("nav", "mapper"), ("nav", "planner"), ("speech", "asr")]


def test_revert_without_migrations_stops_nothing() -> None:
    assert plan_revert({}) == []


# --------------------------------------------------------------------------- CloudMonitor


def test_silence_for_the_delay_triggers_one_takeover() -> None:
    monitor = CloudMonitor(15.0, now=0.0)
    assert monitor.on_message(1.0) is None
    assert monitor.tick(15.9) is None  # 14.9 s of silence
    assert monitor.tick(16.0) == "takeover"  # 15 s: the delay is reached, not exceeded
    assert monitor.taken_over
    assert monitor.tick(17.0) is None
    assert monitor.on_disconnect(18.0) is None


def test_the_cloud_coming_back_reverts_the_takeover_once() -> None:
    monitor = CloudMonitor(15.0, now=0.0)
    assert monitor.tick(15.0) == "takeover"
    assert monitor.on_message(20.0) == "revert"
    assert not monitor.taken_over
    assert monitor.on_message(21.0) is None


def test_a_disconnection_counts_from_the_last_message() -> None:
    monitor = CloudMonitor(15.0, now=0.0)
    monitor.on_message(10.0)
    assert monitor.on_disconnect(12.0) is None
    assert monitor.tick(24.9) is None
    assert monitor.on_disconnect(25.0) == "takeover"


def test_a_quick_reconnection_does_not_take_over() -> None:
    monitor = CloudMonitor(15.0, now=0.0)
    assert monitor.on_disconnect(5.0) is None
    assert monitor.on_message(6.0) is None
    assert monitor.tick(20.9) is None  # 14.9 s after the reconnection
    assert monitor.tick(21.0) == "takeover"


def test_a_late_stamped_message_does_not_move_the_last_contact_back() -> None:
    monitor = CloudMonitor(15.0, now=0.0)
    monitor.on_message(10.0)
    monitor.on_message(4.0)
    assert monitor.last_seen == 10.0
    assert monitor.tick(20.0) is None


def test_a_second_takeover_needs_a_new_silence() -> None:
    monitor = CloudMonitor(15.0, now=0.0)
    assert monitor.tick(15.0) == "takeover"
    assert monitor.on_message(16.0) == "revert"
    assert monitor.tick(30.9) is None
    assert monitor.tick(31.0) == "takeover"


@pytest.mark.parametrize("delay", [0.0, -1.0, math.inf, math.nan])
def test_the_delay_must_be_a_positive_finite_duration(delay: float) -> None:
    with pytest.raises(ValueError, match="disconnection_delay must be a positive number of seconds"):
        CloudMonitor(delay, now=0.0)


# --------------------------------------------------------------------------- properties

amounts = st.integers(min_value=0, max_value=6).map(float)
resources = st.builds(Resources, amounts, amounts, amounts, amounts, amounts)
LOCATIONS: dict[Location, list[ActiveLocation]] = {
    "robot": ["robot", "cloud", None],
    "cloud": ["cloud", None],
    "either": ["robot", "cloud", None],
}
REQUIRED_LOCATIONS: list[Location] = ["either", "either", "robot", "cloud"]


Fleet = dict[str, dict[str, ComponentSnapshot]]


@st.composite
def fleets(draw: st.DrawFn) -> Fleet:
    """Up to four Skills of up to four components placed anywhere their location allows."""
    fleet = {}
    for s in range(draw(st.integers(0, 4))):
        components = {}
        for c in range(draw(st.integers(1, 4))):
            required_location = draw(st.sampled_from(REQUIRED_LOCATIONS))
            active = draw(st.sampled_from(LOCATIONS[required_location]))
            components[f"c{c}"] = ComponentSnapshot(required_location, active, draw(resources))
        fleet[f"s{s}"] = components
    return fleet


@settings(max_examples=400, deadline=None)
@given(fleets(), resources)
def test_a_takeover_plan_never_exceeds_the_free_resources(fleet: Fleet, free: Resources) -> None:
    plan = plan_takeover(fleet, free)
    claimed = ZERO
    for skill_id, taken in plan.items():
        for component_id in taken:
            claimed += fleet[skill_id][component_id].required
    assert claimed.fits(free)


@settings(max_examples=400, deadline=None)
@given(fleets(), resources)
def test_a_takeover_plan_launches_whole_cloud_parts_of_restorable_skills(fleet: Fleet, free: Resources) -> None:
    plan = plan_takeover(fleet, free)
    remaining = free
    for skill_id, components in fleet.items():
        cloud_part = [c for c, comp in components.items() if comp.active_location == "cloud"]
        blocked = any(components[c].required_location == "cloud" for c in cloud_part)
        needed = ZERO
        for c in cloud_part:
            needed += components[c].required
        if skill_id in plan:
            assert not blocked
            assert plan[skill_id] == cloud_part
            remaining -= needed
        else:
            # Skipped only for a reason: nothing in the cloud, a cloud-only part, or no room left.
            assert not cloud_part or blocked or not needed.fits(remaining)


@settings(max_examples=400, deadline=None)
@given(fleets(), resources)
def test_revert_stops_exactly_what_takeover_started(fleet: Fleet, free: Resources) -> None:
    plan = plan_takeover(fleet, free)
    stops = plan_revert(plan)
    started = [(s, c) for s, taken in plan.items() for c in taken]
    assert sorted(stops) == sorted(started)
    assert len(set(stops)) == len(stops)


events = st.lists(
    st.tuples(st.sampled_from(["message", "disconnect", "tick"]), st.floats(min_value=0, max_value=20)),
    max_size=40,
)


@settings(max_examples=400, deadline=None)
@given(st.floats(min_value=0.5, max_value=30), events)
def test_the_monitor_alternates_takeover_and_revert_at_the_right_moments(
    delay: float, steps: list[tuple[str, float]]
) -> None:
    monitor = CloudMonitor(delay, now=0.0)
    now = last_message = 0.0
    expected_next = "takeover"
    for kind, elapsed in steps:
        now += elapsed
        transition = {"message": monitor.on_message, "disconnect": monitor.on_disconnect, "tick": monitor.tick}[kind](
            now
        )
        if kind == "message":
            # A message never takes over, and reverts exactly when a takeover is active.
            assert transition == ("revert" if expected_next == "revert" else None)
            last_message = now
        elif expected_next == "takeover":
            # Takeover happens at the first check after the delay, and never before it.
            assert transition == ("takeover" if now - last_message >= delay else None)
        else:
            assert transition is None
        if transition is not None:
            assert transition == expected_next
            expected_next = "revert" if transition == "takeover" else "takeover"
        assert monitor.taken_over == (expected_next == "revert")
