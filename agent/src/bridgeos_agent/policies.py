"""Compute offloading policy costs per location (thesis section 4.2, equations 4.1-4.6).

Pure: a PolicyEstimator holds the robot's and Skill's constants, and turns one
component's resource usage and metrics into each location's cost under a policy. Every
policy is a cost seen from the robot, so lower is better and the expected migration
reward of leaving a location is the cost there minus the cost at the other location.

Units: resource usage and capacities as in the configs (cores, GPUs, MiB, Mbit/s,
MB/s); energy in watts (Ec is the hourly consumption at full use, so a share of it is
watt-hours per hour); traffic in GB per hour; prices per kWh, per GB and per hour, so
monetary costs are money per hour.

User cost functions (ManagerConfig.cost_functions) are expressions (bridgeos_agent.
expressions) keyed ``robot`` / ``cloud`` for the ``custom`` policy, or
``<policy>_robot`` / ``<policy>_cloud`` to override a built-in policy at one location
or to add a new policy. They may read the variables in ``cost_function_names``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Literal

from bridgeos_agent.expressions import CompiledExpression, ExpressionError, compile_expression
from bridgeos_agent.heuristics import Resources

if TYPE_CHECKING:
    from bridgeos_agent.robotconfig import RobotConfig
    from bridgeos_agent.skillconfig import ManagerConfig

__all__ = [
    "BUILTIN_POLICIES",
    "LOCATIONS",
    "RESOURCE_KINDS",
    "Constants",
    "Metrics",
    "PolicyCosts",
    "PolicyEstimator",
    "cost_function_issues",
    "cost_function_names",
    "energy_cost",
    "monetary_cost",
    "network_cost",
    "parse_cost_function_key",
    "performance_cost",
]

Site = Literal["robot", "cloud"]
LOCATIONS: tuple[Site, Site] = ("robot", "cloud")
BUILTIN_POLICIES = ("energy", "network", "monetary", "performance")
RESOURCE_KINDS = ("cpu", "gpu", "ram", "bandwidth", "io")
# Robot energy keys that are network interfaces (RWI of eq. 4.2) rather than compute.
DEFAULT_WIRELESS = frozenset({"wifi"})
# Variables every cost function may read besides the Skill's own constants.
METRIC_NAMES = ("gb_local", "gb_cloud", "gb_total", "latency", "loss_rate", "ros")
# The robot's state as last measured: free CPU cores, free RAM MiB, link Mbit/s, battery %.
ROBOT_STATE_NAMES = ("cpu_free", "ram_free", "bandwidth_available", "battery")
PRICE_NAMES = ("per_gb", "per_kwh")


@dataclass(frozen=True, slots=True)
class Constants:
    """Hold the robot's and cloud's constants the cost functions are computed from."""

    # Robot capacity: a usage over it is the share S_h of eq. 4.1.
    robot: Resources = field(default_factory=Resources)
    # Capacity the cloud prices C_r refer to ("at full use"): a usage over it is S_r of eq. 4.6.
    cloud: Resources = field(default_factory=Resources)
    # Ec: hourly energy consumption in watts of each robot resource at full use.
    energy: Mapping[str, float] = field(default_factory=dict)
    # C_GB and C_KW of eq. 4.5-4.6.
    per_gb: float = 0.0
    per_kwh: float = 0.0
    # C_r of eq. 4.6: hourly price of each cloud resource at full use.
    cloud_prices: Mapping[str, float] = field(default_factory=dict)
    # RWI of eq. 4.2: the energy keys that are the robot's wireless interfaces.
    wireless: frozenset[str] = DEFAULT_WIRELESS
    # The Skill's own named constants (ManagerConfig.constants), for user cost functions.
    user: Mapping[str, float] = field(default_factory=dict)

    @classmethod
    def of(cls, robot: RobotConfig, manager: ManagerConfig, cloud: Resources) -> Constants:
        """Gather the constants from a robot config, a Skill's manager config and the cloud capacity."""
        return cls(
            robot=Resources.of(robot.resources),
            cloud=cloud,
            energy=MappingProxyType(dict(robot.energy)),
            per_gb=robot.costs.per_gb,
            per_kwh=robot.costs.per_kwh,
            cloud_prices=MappingProxyType(dict(robot.costs.cloud)),
            user=MappingProxyType(dict(manager.constants)),
        )


@dataclass(frozen=True, slots=True)
class Metrics:
    """Hold a component's measured statistics over the last decision interval."""

    # BW_local / BW_cloud: GB per hour the component exchanged with robot / cloud components.
    gb_local: float = 0.0
    gb_cloud: float = 0.0
    # Performance measured while running at each location: network latency (s) and
    # ROS message loss rate (0-1); a location it never ran at keeps its last known value.
    latency_robot: float = 0.0
    latency_cloud: float = 0.0
    loss_rate_robot: float = 0.0
    loss_rate_cloud: float = 0.0
    # The robot's state when the decision is taken (same at both locations): free CPU cores and
    # RAM MiB with the component on the robot (for one in the cloud: what a move there would
    # leave), the link's available bandwidth (Mbit/s) and the battery charge (%, 100 on mains).
    cpu_free: float = 0.0
    ram_free: float = 0.0
    bandwidth_available: float = 0.0
    battery: float = 100.0

    @property
    def gb_total(self) -> float:
        """Return BW_total, everything the component exchanged."""
        return self.gb_local + self.gb_cloud

    def latency(self, location: Site) -> float:
        """Return the latency measured at one location."""
        return self.latency_robot if location == "robot" else self.latency_cloud

    def loss_rate(self, location: Site) -> float:
        """Return the ROS message loss rate measured at one location."""
        return self.loss_rate_robot if location == "robot" else self.loss_rate_cloud


@dataclass(frozen=True, slots=True)
class PolicyCosts:
    """Hold one policy's cost at each location and the reward of leaving the active one."""

    policy: str
    location: Site
    cost_robot: float
    cost_cloud: float

    @property
    def reward(self) -> float:
        """Return the expected migration reward: the cost saved by moving to the other location."""
        here, there = (
            (self.cost_robot, self.cost_cloud) if self.location == "robot" else (self.cost_cloud, self.cost_robot)
        )
        return here - there

    def cost(self, location: Site) -> float:
        """Return the cost at one location."""
        return self.cost_robot if location == "robot" else self.cost_cloud


def _share(used: float, capacity: float) -> float:
    """Return the share of a capacity in use, 0 when there is no such capacity."""
    return used / capacity if capacity > 0 else 0.0


def network_cost(location: Site, usage: Resources, metrics: Metrics) -> float:
    """Compute eq. 4.3 (robot) or 4.4 (cloud): network I/O crossing to the opposite location."""
    # Network_IO is the component's network usage (Mbit/s); the fraction of its traffic
    # exchanged with the opposite location (BW_cloud or BW_local over BW_total) is what
    # would cross the robot-cloud link while it runs at this location.
    if metrics.gb_total <= 0:
        return 0.0
    opposite = metrics.gb_cloud if location == "robot" else metrics.gb_local
    # The share first: bandwidth * opposite could underflow for tiny traffic (5e-324 GB).
    return usage.bandwidth * (opposite / metrics.gb_total)


def energy_cost(location: Site, usage: Resources, metrics: Metrics, constants: Constants) -> float:
    """Compute eq. 4.1 (robot) or 4.2 (cloud): sum of S * Ec over the robot resources used."""
    # S_i of a wireless interface: the share of the robot's bandwidth the component's
    # robot-cloud traffic takes (eq. 4.3/4.4), since only that crosses the radio.
    radio_share = _share(network_cost(location, usage, metrics), constants.robot.bandwidth)
    total = 0.0
    for resource, ec in constants.energy.items():
        if resource in constants.wireless:
            share = radio_share
        elif location == "cloud":
            # RWI only: a cloud component spends no robot CPU, RAM, GPU or disk.
            continue
        elif resource in RESOURCE_KINDS:
            share = _share(getattr(usage, resource), getattr(constants.robot, resource))
        else:
            # An energy entry for hardware the component's usage does not measure (a lidar, ...).
            continue
        total += share * ec
    return total


def monetary_cost(location: Site, usage: Resources, metrics: Metrics, constants: Constants) -> float:
    """Compute eq. 4.5 (robot) or 4.6 (cloud): energy, traffic and cloud resources priced per hour."""
    # E_total / E_wireless in kW: eq. 4.1 / 4.2 give watts, an hour of which is kWh.
    kilowatts = energy_cost(location, usage, metrics, constants) / 1000
    if location == "robot":
        # BW_cloud * C_GB: traffic with cloud components is what the robot pays to send.
        return kilowatts * constants.per_kwh + metrics.gb_cloud * constants.per_gb
    rented = sum(
        _share(getattr(usage, resource), getattr(constants.cloud, resource)) * price
        for resource, price in constants.cloud_prices.items()
        if resource in RESOURCE_KINDS
    )
    return kilowatts * constants.per_kwh + metrics.gb_local * constants.per_gb + rented


def performance_cost(location: Site, ros: bool, metrics: Metrics) -> float:
    """Compute the performance cost: message loss rate for ROS nodes, latency otherwise."""
    return metrics.loss_rate(location) if ros else metrics.latency(location)


def parse_cost_function_key(key: str) -> tuple[str, Site]:
    """Split a cost function key into its policy and location ('robot' means custom at robot)."""
    if key in LOCATIONS:
        return "custom", key
    policy, _, location = key.rpartition("_")
    if not policy or location not in LOCATIONS:
        raise ValueError(f"cost function key {key!r} must be 'robot', 'cloud', '<policy>_robot' or '<policy>_cloud'")
    return policy, location


def cost_function_names(user_constants: Iterable[str] = ()) -> frozenset[str]:
    """Return the variables a cost function may read: resources, metrics, costs, prices, constants."""
    return frozenset(
        (*RESOURCE_KINDS, *METRIC_NAMES, *ROBOT_STATE_NAMES, *PRICE_NAMES, *BUILTIN_POLICIES, *user_constants)
    )


def cost_function_issues(cost_functions: Mapping[str, str], constants: Iterable[str]) -> list[tuple[str | None, str]]:
    """Report every malformed, unsafe or one-sided cost function, keyed by its name."""
    if not cost_functions:
        return []
    issues: list[tuple[str | None, str]] = []
    clash = sorted(set(constants) & cost_function_names())
    if clash:
        issues.append((None, f"constants {', '.join(map(repr, clash))} shadow built-in cost function variables"))
    names = cost_function_names(constants)
    keys: set[tuple[str, Site]] = set()
    for key, text in cost_functions.items():
        try:
            keys.add(parse_cost_function_key(key))
            compile_expression(text, names)
        except ValueError as exc:
            issues.append((key, str(exc)))
    for policy, location in sorted(keys):
        other: Site = "cloud" if location == "robot" else "robot"
        # A built-in policy falls back to its own equation; 'custom' is checked where the policy is chosen.
        if policy not in (*BUILTIN_POLICIES, "custom") and (policy, other) not in keys:
            issues.append((f"{policy}_{location}", f"policy {policy!r} needs a cost function for {other!r} too"))
    return issues


class PolicyEstimator:
    """Compute each location's cost of a component under the built-in and user policies."""

    def __init__(self, constants: Constants, cost_functions: Mapping[str, str] | None = None) -> None:
        cost_functions = cost_functions or {}
        issues = cost_function_issues(cost_functions, constants.user)
        if issues:
            raise ValueError("; ".join(message if key is None else f"{key}: {message}" for key, message in issues))
        names = cost_function_names(constants.user)
        self.constants = constants
        self.functions: Mapping[tuple[str, Site], CompiledExpression] = MappingProxyType(
            {parse_cost_function_key(key): compile_expression(text, names) for key, text in cost_functions.items()}
        )

    @classmethod
    def of(cls, robot: RobotConfig, manager: ManagerConfig, cloud: Resources) -> PolicyEstimator:
        """Build an estimator from a robot config, a Skill's manager config and the cloud capacity."""
        return cls(Constants.of(robot, manager, cloud), manager.cost_functions)

    @property
    def policies(self) -> tuple[str, ...]:
        """Return every policy this estimator can cost, built-in first."""
        extra = sorted({policy for policy, _ in self.functions} - set(BUILTIN_POLICIES))
        return (*BUILTIN_POLICIES, *extra)

    def builtin_cost(self, policy: str, location: Site, usage: Resources, metrics: Metrics, ros: bool) -> float:
        """Return a built-in policy's cost at one location, ignoring user overrides."""
        if policy == "energy":
            return energy_cost(location, usage, metrics, self.constants)
        if policy == "network":
            return network_cost(location, usage, metrics)
        if policy == "monetary":
            return monetary_cost(location, usage, metrics, self.constants)
        if policy == "performance":
            return performance_cost(location, ros, metrics)
        raise ValueError(f"unknown built-in policy {policy!r}")

    def variables(self, location: Site, usage: Resources, metrics: Metrics, ros: bool) -> dict[str, float]:
        """Return the variables a user cost function reads at one location."""
        constants = self.constants
        variables = {kind: float(getattr(usage, kind)) for kind in RESOURCE_KINDS}
        variables.update(
            gb_local=metrics.gb_local,
            gb_cloud=metrics.gb_cloud,
            gb_total=metrics.gb_total,
            latency=metrics.latency(location),
            loss_rate=metrics.loss_rate(location),
            ros=1.0 if ros else 0.0,
            cpu_free=metrics.cpu_free,
            ram_free=metrics.ram_free,
            bandwidth_available=metrics.bandwidth_available,
            battery=metrics.battery,
            per_gb=constants.per_gb,
            per_kwh=constants.per_kwh,
        )
        for policy in BUILTIN_POLICIES:
            variables[policy] = self.builtin_cost(policy, location, usage, metrics, ros)
        variables.update(constants.user)
        return variables

    def cost(self, policy: str, location: Site, usage: Resources, metrics: Metrics, ros: bool = False) -> float:
        """Return one policy's cost at one location, a user cost function taking precedence."""
        function = self.functions.get((policy, location))
        if function is not None:
            try:
                return function.evaluate(self.variables(location, usage, metrics, ros))
            except ExpressionError as exc:
                key = location if policy == "custom" else f"{policy}_{location}"
                raise ValueError(f"cost function {key!r}: {exc}") from None
        if policy in BUILTIN_POLICIES:
            return self.builtin_cost(policy, location, usage, metrics, ros)
        raise ValueError(f"no cost function for policy {policy!r} at {location!r}")

    def estimate(
        self, policy: str, location: Site, usage: Resources, metrics: Metrics, ros: bool = False
    ) -> PolicyCosts:
        """Cost a component at both locations under one policy, given where it runs now."""
        return PolicyCosts(
            policy=policy,
            location=location,
            cost_robot=self.cost(policy, "robot", usage, metrics, ros),
            cost_cloud=self.cost(policy, "cloud", usage, metrics, ros),
        )

    def estimate_all(
        self, location: Site, usage: Resources, metrics: Metrics, ros: bool = False
    ) -> dict[str, PolicyCosts]:
        """Cost a component at both locations under every policy this estimator knows."""
        return {policy: self.estimate(policy, location, usage, metrics, ros) for policy in self.policies}
