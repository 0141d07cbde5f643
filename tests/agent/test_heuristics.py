"""Test the five replacement heuristics (thesis Algorithms 2-6) on hand-worked swaps."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, get_args

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridgeos_agent.heuristics import (
    GIB,
    HEURISTICS,
    KINDS,
    ZERO,
    Resources,
    Swap,
    Weights,
    local_share,
    migration_cost,
    resource_expenditure,
    resource_usage,
    temporal_cost,
    weighted_cost,
)
from bridgeos_agent.robotconfig import Heuristic, HeuristicWeights, RobotResources


@dataclass(frozen=True)
class Member:
    """A running component that would migrate with the replacement."""

    usage: Resources = ZERO
    local_bandwidth: float = 0.0
    cloud_bandwidth: float = 0.0
    volume_bytes: float = 0.0
    ros_bytes: float = 0.0


# A robot with 10 cores, no GPU, 1000 MiB, 100 Mbit/s and 100 MB/s.
TOTAL = Resources(cpu=10, gpu=0, ram=1000, bandwidth=100, io=100)
REQUIRED = Resources(cpu=2, ram=500, bandwidth=20, io=20)
AVAILABLE = Resources(cpu=3, ram=900, bandwidth=60, io=30)

# A: 1 GiB of volume, 0.25 GiB of ROS messages, 30 Mbit/s of which 12 local and 4 cloud.
# B: 0.5 GiB of volume, 0.25 GiB of ROS messages, 8 Mbit/s, no traffic measured.
GROUP = (
    Member(Resources(bandwidth=30), local_bandwidth=12, cloud_bandwidth=4, volume_bytes=GIB, ros_bytes=GIB / 4),
    Member(Resources(bandwidth=8), volume_bytes=GIB / 2, ros_bytes=GIB / 4),
)
WEIGHTS = Weights(gain=1.0, cost=0.5, loss=0.01, time=0.001)


# 42.5 Mbit/s are free while the group still runs.
SWAP = Swap(REQUIRED, AVAILABLE, TOTAL, Resources(bandwidth=42.5), GROUP, per_gb=0.1, weights=WEIGHTS)


def swap(**changes: Any) -> Swap:
    """Return the hand-worked swap, with some fields changed."""
    return replace(SWAP, **changes)


# --------------------------------------------------------------------------- Resources


def test_resources_add_and_subtract_per_kind() -> None:
    a = Resources(1, 2, 3, 4, 5)
    b = Resources(0.5, 1, 1, 1, 1)
    assert a + b == Resources(1.5, 3, 4, 5, 6)
    assert a - b == Resources(0.5, 1, 2, 3, 4)


def test_fits_needs_every_kind_to_fit() -> None:
    capacity = Resources(2, 1, 1024, 100, 50)
    assert Resources(2, 1, 1024, 100, 50).fits(capacity)
    for kind in KINDS:
        over = Resources(**{kind: getattr(capacity, kind) + 0.001})
        assert not over.fits(capacity)
        assert over.short_of(capacity) == (kind,)


def test_fits_forgives_float_rounding() -> None:
    # 0.1 + 0.2 is 0.30000000000000004 in binary floating point.
    assert Resources(cpu=0.1 + 0.2).fits(Resources(cpu=0.3))
    assert not Resources(cpu=0.3 + 1e-6).fits(Resources(cpu=0.3))


def test_resources_of_copies_a_config_model() -> None:
    robot = RobotResources(cpu=4, gpu=1, ram=8192, bandwidth=300, io=250)
    assert Resources.of(robot) == Resources(4.0, 1.0, 8192.0, 300.0, 250.0)


def test_weights_of_copies_the_config_weights() -> None:
    assert Weights.of(HeuristicWeights(gain=2, cost=3, loss=4, time=5)) == Weights(2, 3, 4, 5)


# --------------------------------------------------------------------------- Algorithm 2


def test_resource_usage_is_the_geometric_mean_of_idle_shares() -> None:
    result = resource_usage(swap())
    # cpu (3 - 2) / 10 = 0.1, ram (900 - 500) / 1000 = 0.4,
    # bandwidth (60 - 20) / 100 = 0.4, io (30 - 20) / 100 = 0.1; the robot has no GPU.
    assert result.ratios == Resources(cpu=0.1, gpu=0.0, ram=0.4, bandwidth=0.4, io=0.1)
    # (0.1 * 0.4 * 0.4 * 0.1) ** (1/4) = 0.0016 ** 0.25 = 0.2: the missing GPU is left
    # out, or the product would be 0 on every GPU-less robot.
    assert result.average == pytest.approx(0.2)


def test_resource_usage_is_infinite_when_the_swap_frees_too_little() -> None:
    result = resource_usage(swap(available=AVAILABLE - Resources(ram=401)))
    # ram (499 - 500) / 1000 < 0: the swap is no solution.
    assert result.ratios.ram == math.inf
    assert result.ratios.cpu == pytest.approx(0.1)
    assert result.average == math.inf


def test_resource_usage_of_a_gpu_on_a_gpu_less_robot_is_infinite() -> None:
    result = resource_usage(swap(required=REQUIRED + Resources(gpu=1)))
    assert result.ratios.gpu == math.inf
    assert result.average == math.inf


def test_resource_usage_with_no_capacity_at_all_is_zero() -> None:
    result = resource_usage(swap(required=ZERO, available=ZERO, total=ZERO))
    assert result.ratios == ZERO
    assert result.average == 0.0


def test_resource_usage_of_an_exact_fit_is_zero() -> None:
    # Zero waste on one kind is the thesis's optimum, so the mean is 0.
    result = resource_usage(swap(available=AVAILABLE - Resources(io=10)))
    assert result.ratios.io == 0.0
    assert result.average == 0.0


def test_resource_usage_tolerates_rounding_at_an_exact_fit() -> None:
    result = resource_usage(
        swap(required=REQUIRED + Resources(cpu=0.1 + 0.2), available=AVAILABLE - Resources(cpu=0.7))
    )
    # available cpu 3 - 0.7 = 2.3 against required 2 + (0.1 + 0.2) = 2.3000000000000003: a fit.
    assert result.ratios.cpu == 0.0
    assert result.average == 0.0


# --------------------------------------------------------------------------- Algorithm 3


def test_migration_cost_adds_the_group_state_and_prices_it() -> None:
    result = migration_cost(swap())
    # volumes 1 + 0.5 GiB, ROS messages 0.25 + 0.25 GiB, 2 GiB at 0.1 per GB = 0.2.
    assert result.state_transfer == 1.5 * GIB
    assert result.ros_synchronization == 0.5 * GIB
    assert result.total == 2 * GIB
    assert result.cost == pytest.approx(0.2)


def test_migration_cost_of_a_stateless_group_is_zero() -> None:
    result = migration_cost(swap(group=(Member(), Member())))
    assert (result.state_transfer, result.ros_synchronization, result.total, result.cost) == (0, 0, 0, 0)


def test_migration_cost_on_a_free_network_still_counts_bytes() -> None:
    result = migration_cost(swap(per_gb=0.0))
    assert result.total == 2 * GIB
    assert result.cost == 0.0


# --------------------------------------------------------------------------- Algorithm 4


def test_local_share_is_the_local_part_of_the_traffic() -> None:
    assert local_share(12, 4) == 0.75
    assert local_share(5, 0) == 1.0
    assert local_share(0, 5) == 0.0


def test_local_share_without_traffic_is_zero_not_a_division_by_zero() -> None:
    assert local_share(0, 0) == 0.0


def test_resource_expenditure_weighs_waste_size_and_network_loss() -> None:
    result = resource_expenditure(swap())
    # variation: A 30 * 12 / (12 + 4) = 22.5 Mbit/s, B has no traffic measured: 0.
    assert result.variation == pytest.approx(22.5)
    # 0.2 (waste) * 1 + 2 (GiB) * 0.5 + 22.5 (Mbit/s) * 0.01 = 0.2 + 1 + 0.225 = 1.425
    assert result.expenditure == pytest.approx(1.425)


def test_resource_expenditure_counts_all_traffic_of_a_purely_local_component() -> None:
    result = resource_expenditure(swap(group=(Member(Resources(bandwidth=30), local_bandwidth=7),)))
    assert result.variation == 30.0


def test_resource_expenditure_keeps_an_infeasible_swap_infinite_at_weight_zero() -> None:
    result = resource_expenditure(swap(available=ZERO, weights=Weights(gain=0.0)))
    # The waste term is infinite; inf * 0 would be NaN and compare false with everything.
    assert result.expenditure == math.inf


# --------------------------------------------------------------------------- Algorithm 5


def test_temporal_cost_is_the_transfer_time_over_spare_bandwidth() -> None:
    # spare = 42.5 - 22.5 = 20 Mbit/s; 2 GiB = 2 * 2**30 * 8 = 17_179_869_184 bits;
    # 17_179_869_184 / 20e6 = 858.9934592 s.
    assert temporal_cost(swap()) == pytest.approx(858.9934592)


@pytest.mark.parametrize("free_bandwidth", [22.5, 10.0, 0.0])
def test_temporal_cost_without_spare_bandwidth_is_infinite(free_bandwidth: float) -> None:
    # 22.5 - 22.5 = 0 and below: the migrated group alone would saturate the link.
    assert temporal_cost(swap(free=Resources(bandwidth=free_bandwidth))) == math.inf


def test_temporal_cost_of_a_stateless_group_is_zero() -> None:
    assert temporal_cost(swap(group=(Member(Resources(bandwidth=30)),))) == 0.0


# --------------------------------------------------------------------------- Algorithm 6


def test_weighted_cost_weighs_expenditure_against_time() -> None:
    # 1.425 * 0.5 (cost) + 858.9934592 * 0.001 (time) = 0.7125 + 0.8589934592
    assert weighted_cost(swap()) == pytest.approx(1.5714934592)


def test_weighted_cost_of_an_endless_migration_is_infinite_even_at_time_weight_zero() -> None:
    chosen = swap(free=Resources(bandwidth=1.0), weights=Weights(time=0.0))
    assert temporal_cost(chosen) == math.inf
    assert weighted_cost(chosen) == math.inf


# --------------------------------------------------------------------------- registry


def test_registry_offers_exactly_the_configurable_heuristics() -> None:
    assert set(HEURISTICS) == set(get_args(Heuristic))


def test_registry_returns_each_heuristic_comparable_cost() -> None:
    chosen = swap()
    assert HEURISTICS["resource_usage"](chosen) == pytest.approx(0.2)
    assert HEURISTICS["migration_cost"](chosen) == pytest.approx(0.2)
    assert HEURISTICS["resource_expenditure"](chosen) == pytest.approx(1.425)
    assert HEURISTICS["temporal_cost"](chosen) == pytest.approx(858.9934592)
    assert HEURISTICS["weighted_cost"](chosen) == pytest.approx(1.5714934592)


# --------------------------------------------------------------------------- properties

amounts = st.integers(min_value=0, max_value=16).map(float)
resources = st.builds(Resources, amounts, amounts, amounts, amounts, amounts)
members = st.builds(
    Member,
    resources,
    amounts,
    amounts,
    st.integers(min_value=0, max_value=4 * GIB).map(float),
    st.integers(min_value=0, max_value=4 * GIB).map(float),
)
weights = st.builds(Weights, amounts, amounts, amounts, amounts)
swaps = st.builds(
    Swap,
    resources,
    resources,
    resources,
    resources,
    st.lists(members, max_size=4).map(tuple),
    st.sampled_from([0.0, 0.1, 2.5]),
    weights,
)


@settings(max_examples=300, deadline=None)
@given(swaps)
def test_resource_usage_is_finite_exactly_when_the_swap_frees_enough(chosen: Swap) -> None:
    result = resource_usage(chosen)
    assert math.isfinite(result.average) == chosen.required.fits(chosen.available)
    assert result.average >= 0


@settings(max_examples=300, deadline=None)
@given(swaps)
def test_resource_usage_mean_lies_between_the_counted_ratios(chosen: Swap) -> None:
    result = resource_usage(chosen)
    counted = [getattr(result.ratios, k) for k in KINDS if getattr(chosen.total, k) > 0]
    if counted and result.average != math.inf:
        assert min(counted) - 1e-12 <= result.average <= max(counted) + 1e-12


@settings(max_examples=300, deadline=None)
@given(swaps, st.sampled_from(sorted(HEURISTICS)))
def test_every_heuristic_gives_a_non_negative_comparable_cost(chosen: Swap, name: str) -> None:
    cost = HEURISTICS[name](chosen)
    assert not math.isnan(cost)
    assert cost >= 0


@settings(max_examples=200, deadline=None)
@given(swaps, members)
def test_a_bigger_group_never_migrates_fewer_bytes(chosen: Swap, extra: Member) -> None:
    before = migration_cost(chosen)
    after = migration_cost(swap(group=(*chosen.group, extra), per_gb=chosen.per_gb))
    assert after.total == before.total + extra.volume_bytes + extra.ros_bytes
    assert after.cost >= before.cost
