"""Test the offloading policy cost functions (thesis equations 4.1-4.6) and user cost functions."""

from __future__ import annotations

from types import MappingProxyType

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from bridgeos_agent.heuristics import Resources
from bridgeos_agent.policies import (
    BUILTIN_POLICIES,
    Constants,
    Metrics,
    PolicyCosts,
    PolicyEstimator,
    cost_function_issues,
    cost_function_names,
    energy_cost,
    monetary_cost,
    network_cost,
    parse_cost_function_key,
    performance_cost,
)
from bridgeos_agent.robotconfig import RobotConfig
from bridgeos_agent.skillconfig import ManagerConfig

CONSTANTS = Constants(
    robot=Resources(cpu=2, gpu=1, ram=2048, bandwidth=100, io=100),
    cloud=Resources(cpu=4, gpu=0, ram=8192, bandwidth=1000, io=500),
    energy=MappingProxyType({"cpu": 10.0, "gpu": 0.0, "ram": 2.0, "io": 1.5, "wifi": 2.5, "lidar": 8.0}),
    per_gb=0.1,
    per_kwh=0.25,
    cloud_prices=MappingProxyType({"cpu": 0.2, "ram": 0.1, "tpu": 9.0}),
    user=MappingProxyType({"weight": 2.0}),
)
USAGE = Resources(cpu=0.5, gpu=0, ram=512, bandwidth=20, io=10)
METRICS = Metrics(
    gb_local=3.0,
    gb_cloud=1.0,
    latency_robot=0.01,
    latency_cloud=0.05,
    loss_rate_robot=0.0,
    loss_rate_cloud=0.02,
)


def test_network_cost_on_the_robot_is_the_share_of_traffic_with_the_cloud() -> None:
    # Eq. 4.3: Network_IO * BW_cloud / BW_total = 20 Mbit/s * 1 GB / (3 + 1) GB.
    assert network_cost("robot", USAGE, METRICS) == pytest.approx(20 * 1 / 4)


def test_network_cost_in_the_cloud_is_the_share_of_traffic_with_the_robot() -> None:
    # Eq. 4.4: Network_IO * BW_local / BW_total = 20 * 3 / 4.
    assert network_cost("cloud", USAGE, METRICS) == pytest.approx(20 * 3 / 4)


def test_network_cost_without_traffic_is_zero() -> None:
    assert network_cost("robot", USAGE, Metrics()) == 0.0
    assert network_cost("cloud", USAGE, Metrics()) == 0.0


def test_energy_cost_on_the_robot_sums_every_hardware_resource_share() -> None:
    # Eq. 4.1: sum of S_h * Ec_h over the robot's hardware resources:
    # cpu 0.5/2 * 10 + gpu 0/1 * 0 + ram 512/2048 * 2 + io 10/100 * 1.5
    # + wifi (eq. 4.3's 5 Mbit/s over 100 Mbit/s) * 2.5; the unmeasured lidar adds nothing.
    expected = 0.5 / 2 * 10 + 0 + 512 / 2048 * 2 + 10 / 100 * 1.5 + 5 / 100 * 2.5
    assert expected == pytest.approx(3.275)
    assert energy_cost("robot", USAGE, METRICS, CONSTANTS) == pytest.approx(expected)


def test_energy_cost_in_the_cloud_counts_only_the_wireless_interfaces() -> None:
    # Eq. 4.2: sum of S_i * Ec_i over RWI = wifi only: (15 Mbit/s / 100 Mbit/s) * 2.5 W.
    assert energy_cost("cloud", USAGE, METRICS, CONSTANTS) == pytest.approx(15 / 100 * 2.5)


def test_energy_cost_honours_other_wireless_interfaces() -> None:
    constants = Constants(
        robot=CONSTANTS.robot,
        energy=MappingProxyType({"cpu": 10.0, "wifi": 2.5, "lte": 4.0}),
        wireless=frozenset({"wifi", "lte"}),
    )
    # Both radios carry the 15 Mbit/s of eq. 4.4 in the cloud: 0.15 * 2.5 + 0.15 * 4.
    assert energy_cost("cloud", USAGE, METRICS, constants) == pytest.approx(0.15 * 2.5 + 0.15 * 4)


def test_monetary_cost_on_the_robot_prices_energy_and_traffic_to_the_cloud() -> None:
    # Eq. 4.5: E_total * C_KW + BW_cloud * C_GB = (3.275 W -> kW) * 0.25 + 1 GB * 0.1.
    expected = 3.275 / 1000 * 0.25 + 1 * 0.1
    assert monetary_cost("robot", USAGE, METRICS, CONSTANTS) == pytest.approx(expected)


def test_monetary_cost_in_the_cloud_adds_rented_cloud_resources() -> None:
    # Eq. 4.6: E_wireless * C_KW + BW_local * C_GB + sum of S_r * C_r:
    # (0.375 W -> kW) * 0.25 + 3 GB * 0.1 + cpu 0.5/4 * 0.2 + ram 512/8192 * 0.1;
    # the tpu price has no usage to share, so it adds nothing.
    expected = 0.375 / 1000 * 0.25 + 3 * 0.1 + 0.5 / 4 * 0.2 + 512 / 8192 * 0.1
    assert expected == pytest.approx(0.33134375)
    assert monetary_cost("cloud", USAGE, METRICS, CONSTANTS) == pytest.approx(expected)


def test_performance_of_a_ros_node_is_its_message_loss_rate() -> None:
    assert performance_cost("robot", True, METRICS) == 0.0
    assert performance_cost("cloud", True, METRICS) == 0.02


def test_performance_of_other_components_is_their_latency() -> None:
    assert performance_cost("robot", False, METRICS) == 0.01
    assert performance_cost("cloud", False, METRICS) == 0.05


def test_estimate_returns_both_costs_and_the_reward_of_leaving() -> None:
    estimator = PolicyEstimator(CONSTANTS)
    costs = estimator.estimate("energy", "robot", USAGE, METRICS)
    assert costs.cost_robot == pytest.approx(3.275)
    assert costs.cost_cloud == pytest.approx(0.375)
    # Leaving the robot saves 3.275 - 0.375 W.
    assert costs.reward == pytest.approx(2.9)
    assert estimator.estimate("energy", "cloud", USAGE, METRICS).reward == pytest.approx(-2.9)


def test_estimate_all_covers_every_builtin_policy() -> None:
    costs = PolicyEstimator(CONSTANTS).estimate_all("cloud", USAGE, METRICS, ros=True)
    assert tuple(costs) == BUILTIN_POLICIES
    assert costs["network"] == PolicyCosts("network", "cloud", 5.0, 15.0)
    assert costs["network"].reward == pytest.approx(10.0)
    assert costs["monetary"].cost("cloud") == pytest.approx(0.33134375)
    assert costs["performance"].reward == pytest.approx(0.02)


def test_policy_costs_are_frozen() -> None:
    costs = PolicyCosts("energy", "robot", 1.0, 2.0)
    with pytest.raises(AttributeError):
        costs.cost_robot = 3.0  # type: ignore[misc]


def test_custom_policy_reads_builtin_costs_metrics_and_constants() -> None:
    estimator = PolicyEstimator(
        CONSTANTS, {"robot": "energy + 10 * latency * weight", "cloud": "monetary * 100 if ros else 0"}
    )
    costs = estimator.estimate("custom", "robot", USAGE, METRICS, ros=True)
    # Robot: 3.275 W + 10 * 0.01 s * 2; cloud: eq. 4.6's 0.33134375 * 100 because ros = 1.
    assert costs.cost_robot == pytest.approx(3.275 + 10 * 0.01 * 2)
    assert costs.cost_cloud == pytest.approx(33.134375)
    assert "custom" in estimator.policies


def test_custom_policy_reads_the_robot_state() -> None:
    estimator = PolicyEstimator(
        CONSTANTS,
        {
            "robot": "cpu / (cpu_free + 0.1) + (1 if battery < 20 else 0)",
            "cloud": "bandwidth / max(bandwidth_available, 1) + ram / ram_free",
        },
    )
    state = Metrics(cpu_free=0.4, ram_free=1024, bandwidth_available=5.0, battery=15.0)
    costs = estimator.estimate("custom", "robot", USAGE, state)
    assert costs.cost_robot == pytest.approx(0.5 / 0.5 + 1)
    assert costs.cost_cloud == pytest.approx(20 / 5 + 512 / 1024)
    # Unmeasured, the robot runs on mains.
    assert Metrics().battery == 100.0


def test_user_function_overrides_one_location_of_a_builtin_policy() -> None:
    estimator = PolicyEstimator(CONSTANTS, {"performance_cloud": "latency + 0.1"})
    costs = estimator.estimate("performance", "cloud", USAGE, METRICS)
    assert costs.cost_robot == 0.01
    assert costs.cost_cloud == pytest.approx(0.05 + 0.1)
    assert costs.reward == pytest.approx(0.14)


def test_user_functions_add_a_new_policy() -> None:
    estimator = PolicyEstimator(CONSTANTS, {"comfort_robot": "cpu * ram / 1024", "comfort_cloud": "gb_total * per_gb"})
    costs = estimator.estimate("comfort", "robot", USAGE, METRICS)
    assert costs.cost_robot == pytest.approx(0.5 * 512 / 1024)
    assert costs.cost_cloud == pytest.approx(4 * 0.1)
    assert estimator.policies == (*BUILTIN_POLICIES, "comfort")


def test_new_policy_needs_both_locations() -> None:
    with pytest.raises(ValueError, match="policy 'comfort' needs a cost function for 'cloud' too"):
        PolicyEstimator(CONSTANTS, {"comfort_robot": "cpu"})


def test_unsafe_cost_function_is_refused_when_the_estimator_is_built() -> None:
    with pytest.raises(ValueError, match=r"^robot: attribute access is not allowed at column 4$"):
        PolicyEstimator(CONSTANTS, {"robot": "cpu.__class__", "cloud": "0"})


def test_cost_function_with_an_unknown_variable_is_refused() -> None:
    with pytest.raises(ValueError, match="unknown name 'batery'"):
        PolicyEstimator(CONSTANTS, {"energy_robot": "batery * 2"})


def test_failing_cost_function_names_its_key() -> None:
    estimator = PolicyEstimator(CONSTANTS, {"network_robot": "1 / gb_total"})
    with pytest.raises(ValueError, match="cost function 'network_robot': division by zero"):
        estimator.cost("network", "robot", USAGE, Metrics())


def test_custom_policy_without_functions_is_an_error() -> None:
    with pytest.raises(ValueError, match="no cost function for policy 'custom' at 'robot'"):
        PolicyEstimator(CONSTANTS).estimate("custom", "robot", USAGE, METRICS)


def test_constants_may_not_shadow_builtin_variables() -> None:
    constants = Constants(user=MappingProxyType({"cpu": 1.0, "latency": 2.0}))
    with pytest.raises(ValueError, match="constants 'cpu', 'latency' shadow"):
        PolicyEstimator(constants, {"energy_robot": "cpu"})


def test_constants_are_free_when_no_cost_function_reads_them() -> None:
    constants = Constants(user=MappingProxyType({"cpu": 1.0}))
    assert PolicyEstimator(constants).policies == BUILTIN_POLICIES


def test_cost_function_issues_lists_every_problem_by_key() -> None:
    issues = cost_function_issues({"robot": "1 +", "energy_either": "1", "comfort_cloud": "cpu"}, ["weight"])
    assert issues == [
        ("robot", "invalid syntax"),
        (
            "energy_either",
            "cost function key 'energy_either' must be 'robot', 'cloud', '<policy>_robot' or '<policy>_cloud'",
        ),
        ("comfort_cloud", "policy 'comfort' needs a cost function for 'robot' too"),
    ]


@pytest.mark.parametrize(
    ("key", "expected"),
    [
        ("robot", ("custom", "robot")),
        ("cloud", ("custom", "cloud")),
        ("energy_robot", ("energy", "robot")),
        ("battery_life_cloud", ("battery_life", "cloud")),
    ],
)
def test_cost_function_keys_name_a_policy_and_a_location(key: str, expected: tuple[str, str]) -> None:
    assert parse_cost_function_key(key) == expected


@pytest.mark.parametrize("key", ["either", "energy", "energy_either", "_robot", "robotcloud"])
def test_malformed_cost_function_keys_are_refused(key: str) -> None:
    with pytest.raises(ValueError, match="must be 'robot', 'cloud'"):
        parse_cost_function_key(key)


def test_cost_function_names_cover_resources_metrics_costs_and_constants() -> None:
    names = cost_function_names(["weight"])
    assert {"cpu", "gpu", "ram", "bandwidth", "io", "latency", "loss_rate", "gb_local", "ros"} <= names
    assert {"energy", "network", "monetary", "performance", "per_gb", "per_kwh", "weight"} <= names
    assert {"cpu_free", "ram_free", "bandwidth_available", "battery"} <= names


def test_estimator_builds_from_robot_and_manager_configs() -> None:
    robot = RobotConfig.model_validate({"costs": {"per_gb": 0.1, "per_kwh": 0.25, "cloud": {"cpu": 0.2}}})
    manager = ManagerConfig.model_validate(
        {"policy": "custom", "constants": {"weight": 3}, "cost_functions": {"robot": "weight * cpu", "cloud": "0"}}
    )
    estimator = PolicyEstimator.of(robot, manager, Resources(cpu=4))
    costs = estimator.estimate(manager.policy, "robot", USAGE, METRICS)
    assert costs.cost_robot == pytest.approx(3 * 0.5)
    # The default robot: 2 cores at 10 W, 2048 MiB at 2 W, 100 MB/s of I/O at 1.5 W, wifi at 2.5 W.
    energy = estimator.cost("energy", "robot", USAGE, METRICS)
    assert energy == pytest.approx(0.25 * 10 + 0.25 * 2 + 0.1 * 1.5 + 0.05 * 2.5)
    # Eq. 4.6 with the default prices: 0.375 W, 3 GB and a 0.5-of-4-core share at 0.2 per hour.
    monetary = estimator.cost("monetary", "cloud", USAGE, METRICS)
    assert monetary == pytest.approx(0.375 / 1000 * 0.25 + 3 * 0.1 + 0.5 / 4 * 0.2)


_amounts = st.floats(min_value=0, max_value=1e4, allow_nan=False, allow_infinity=False)
_usages = st.builds(Resources, cpu=_amounts, gpu=_amounts, ram=_amounts, bandwidth=_amounts, io=_amounts)
_metrics = st.builds(
    Metrics,
    gb_local=_amounts,
    gb_cloud=_amounts,
    latency_robot=_amounts,
    latency_cloud=_amounts,
    loss_rate_robot=st.floats(0, 1),
    loss_rate_cloud=st.floats(0, 1),
)


@settings(max_examples=200, deadline=None)
@given(_usages, _metrics, st.booleans(), st.sampled_from(["robot", "cloud"]))
def test_costs_are_non_negative_for_non_negative_inputs(
    usage: Resources, metrics: Metrics, ros: bool, location: str
) -> None:
    for costs in PolicyEstimator(CONSTANTS).estimate_all(location, usage, metrics, ros).values():  # type: ignore[arg-type]
        assert costs.cost_robot >= 0
        assert costs.cost_cloud >= 0


@settings(max_examples=200, deadline=None)
@given(_usages, _metrics)
# Found by hypothesis: bandwidth * 5e-324 underflowed before the share was taken.
@example(Resources(bandwidth=1.5), Metrics(gb_cloud=5e-324))
def test_network_costs_of_both_locations_add_up_to_the_component_network_io(usage: Resources, metrics: Metrics) -> None:
    total = network_cost("robot", usage, metrics) + network_cost("cloud", usage, metrics)
    expected = usage.bandwidth if metrics.gb_total > 0 else 0.0
    assert total == pytest.approx(expected)


@settings(max_examples=200, deadline=None)
@given(_usages, _metrics, st.sampled_from(BUILTIN_POLICIES))
def test_reward_of_leaving_one_location_is_minus_the_reward_of_leaving_the_other(
    usage: Resources, metrics: Metrics, policy: str
) -> None:
    estimator = PolicyEstimator(CONSTANTS)
    assert (
        estimator.estimate(policy, "robot", usage, metrics).reward
        == -estimator.estimate(policy, "cloud", usage, metrics).reward
    )


@settings(max_examples=100, deadline=None)
@given(_usages, _metrics)
def test_cloud_energy_never_exceeds_robot_energy_for_the_same_radio_traffic(usage: Resources, metrics: Metrics) -> None:
    # Eq. 4.2 sums a subset of eq. 4.1's terms when the radio carries the same traffic.
    balanced = Metrics(gb_local=metrics.gb_local, gb_cloud=metrics.gb_local)
    assert energy_cost("cloud", usage, balanced, CONSTANTS) <= energy_cost("robot", usage, balanced, CONSTANTS) + 1e-9
