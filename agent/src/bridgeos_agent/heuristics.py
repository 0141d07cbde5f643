"""Rank replacement candidates for Algorithm 1 with the five heuristics of thesis section 3.3.1.

Pure: every function reads plain data and returns plain data. A heuristic weighs one
*swap*: moving a group of running components (a replacement and its links) to the cloud
so that a requested component fits on the robot. Lower costs are better.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol

__all__ = [
    "GIB",
    "HEURISTICS",
    "KINDS",
    "TOLERANCE",
    "ZERO",
    "Migrant",
    "MigrationCost",
    "ResourceExpenditure",
    "ResourceUsage",
    "Resources",
    "Swap",
    "Weights",
    "local_share",
    "migration_cost",
    "resource_expenditure",
    "resource_usage",
    "temporal_cost",
    "weighted_cost",
]

# The hardware resource kinds of Algorithm 2, line 1, in that order.
KINDS = ("cpu", "gpu", "ram", "bandwidth", "io")

GIB = 1024**3

# Measured amounts are sums of floats (0.1 + 0.2 > 0.3), so an amount within a billionth
# of a unit of its capacity fits; otherwise rounding alone could refuse a deployment.
TOLERANCE = 1e-9


@dataclass(frozen=True, slots=True)
class Resources:
    """Hold an amount of each resource kind: cores, GPUs, MiB, Mbit/s and MB/s."""

    cpu: float = 0.0
    gpu: float = 0.0
    ram: float = 0.0
    bandwidth: float = 0.0
    io: float = 0.0

    @classmethod
    def of(cls, source: Any) -> Resources:
        """Copy the five kinds from any object that names them, such as a config model."""
        return cls(float(source.cpu), float(source.gpu), float(source.ram), float(source.bandwidth), float(source.io))

    def __add__(self, other: Resources) -> Resources:
        return Resources(
            self.cpu + other.cpu,
            self.gpu + other.gpu,
            self.ram + other.ram,
            self.bandwidth + other.bandwidth,
            self.io + other.io,
        )

    def __sub__(self, other: Resources) -> Resources:
        return Resources(
            self.cpu - other.cpu,
            self.gpu - other.gpu,
            self.ram - other.ram,
            self.bandwidth - other.bandwidth,
            self.io - other.io,
        )

    def fits(self, capacity: Resources) -> bool:
        """Tell whether every kind of this amount fits within the capacity."""
        return (
            self.cpu <= capacity.cpu + TOLERANCE
            and self.gpu <= capacity.gpu + TOLERANCE
            and self.ram <= capacity.ram + TOLERANCE
            and self.bandwidth <= capacity.bandwidth + TOLERANCE
            and self.io <= capacity.io + TOLERANCE
        )

    def short_of(self, capacity: Resources) -> tuple[str, ...]:
        """Name the kinds of this amount that exceed the capacity."""
        return tuple(kind for kind in KINDS if getattr(self, kind) > getattr(capacity, kind) + TOLERANCE)


ZERO = Resources()


@dataclass(frozen=True, slots=True)
class Weights:
    """Weigh the terms of the combined heuristics (Algorithms 4 and 6)."""

    gain: float = 1.0
    cost: float = 1.0
    loss: float = 1.0
    time: float = 1.0

    @classmethod
    def of(cls, source: Any) -> Weights:
        """Copy the four weights from any object that names them, such as HeuristicWeights."""
        return cls(float(source.gain), float(source.cost), float(source.loss), float(source.time))


class Migrant(Protocol):
    """Describe one running component that would move to the cloud in a swap."""

    @property
    def usage(self) -> Resources: ...

    @property
    def local_bandwidth(self) -> float: ...

    @property
    def cloud_bandwidth(self) -> float: ...

    @property
    def volume_bytes(self) -> float: ...

    @property
    def ros_bytes(self) -> float: ...


@dataclass(frozen=True, slots=True)
class Swap:
    """Describe moving a group of components to the cloud so a requested component fits."""

    required: Resources  # the requested component plus its links (Algorithm 1, lines 2-6)
    available: Resources  # free now plus what the group frees (Algorithm 1, lines 23-26)
    total: Resources  # the robot's capacity
    free: Resources  # free now, while the group still runs: the bandwidth its migration can use
    group: Sequence[Migrant] = ()  # the replacement and every component linked to it
    per_gb: float = 0.1
    weights: Weights = field(default_factory=Weights)


@dataclass(frozen=True, slots=True)
class ResourceUsage:
    """Hold Algorithm 2's share of each capacity left idle and their geometric mean."""

    ratios: Resources
    average: float


@dataclass(frozen=True, slots=True)
class MigrationCost:
    """Hold Algorithm 3's bytes to synchronise and the price of sending them."""

    state_transfer: float
    ros_synchronization: float
    total: float
    cost: float


@dataclass(frozen=True, slots=True)
class ResourceExpenditure:
    """Hold Algorithm 4's weighted expenditure and the network usage variation it expects."""

    expenditure: float
    variation: float


def resource_usage(swap: Swap) -> ResourceUsage:
    """Measure the capacity a swap leaves idle, per kind and as one mean (Algorithm 2)."""
    ratios: dict[str, float] = {}
    counted: list[float] = []
    for kind in KINDS:
        spare = getattr(swap.available, kind) - getattr(swap.required, kind)
        total = getattr(swap.total, kind)
        if spare < -TOLERANCE:
            # A negative ratio means the swap does not free enough: it is no solution at
            # all, whatever the other kinds say. Checked before the zero-capacity case so
            # that asking a GPU-less robot for a GPU is infeasible rather than free.
            ratios[kind] = math.inf
            counted.append(math.inf)
        elif total <= 0:
            # The robot lacks this kind, so nothing of it can be wasted. Kept out of the
            # mean: the thesis's ratio of 0 would make every swap on a GPU-less robot cost 0.
            ratios[kind] = 0.0
        else:
            ratios[kind] = max(spare, 0.0) / total
            counted.append(ratios[kind])
    if not counted:
        average = 0.0
    elif math.inf in counted:
        average = math.inf  # and not 0 * inf, which is NaN
    else:
        average = math.prod(counted) ** (1 / len(counted))
    return ResourceUsage(Resources(**ratios), average)


def migration_cost(swap: Swap) -> MigrationCost:
    """Count the bytes a swap synchronises with the cloud and their price (Algorithm 3)."""
    state_transfer = float(sum(migrant.volume_bytes for migrant in swap.group))
    ros_synchronization = float(sum(migrant.ros_bytes for migrant in swap.group))
    total = state_transfer + ros_synchronization
    return MigrationCost(state_transfer, ros_synchronization, total, total / GIB * swap.per_gb)


def local_share(local_bandwidth: float, cloud_bandwidth: float) -> float:
    """Return the share of a component's traffic exchanged on the robot (0 when it has none)."""
    # The thesis guards this division only for the replacement itself (Algorithm 4, line 5)
    # and skips it when either side is 0; one rule for every member is simpler and keeps
    # a purely local component's traffic, which is exactly what a migration moves.
    both = local_bandwidth + cloud_bandwidth
    return local_bandwidth / both if both > 0 else 0.0


def _weigh(value: float, weight: float) -> float:
    """Scale a term, keeping an infinite (infeasible) term infinite even at weight 0."""
    # inf * 0 is NaN, which compares false with every cost and would quietly win or lose.
    return math.inf if math.isinf(value) else value * weight


def _expenditure(swap: Swap, usage: ResourceUsage, migration: MigrationCost) -> ResourceExpenditure:
    """Combine idle capacity, bytes to move and extra network use into one cost."""
    variation = sum(
        migrant.usage.bandwidth * local_share(migrant.local_bandwidth, migrant.cloud_bandwidth)
        for migrant in swap.group
    )
    weights = swap.weights
    # The thesis adds bytes to ratios in [0, 1]; gibibytes (the unit per_gb prices) keep
    # the three terms commensurable, so weights of 1 and the default threshold mean something.
    expenditure = (
        _weigh(usage.average, weights.gain)
        + _weigh(migration.total / GIB, weights.cost)
        + _weigh(variation, weights.loss)
    )
    return ResourceExpenditure(expenditure, variation)


def resource_expenditure(swap: Swap) -> ResourceExpenditure:
    """Weigh idle capacity, migration size and added network use of a swap (Algorithm 4)."""
    return _expenditure(swap, resource_usage(swap), migration_cost(swap))


def _seconds(swap: Swap, migration: MigrationCost, expenditure: ResourceExpenditure) -> float:
    """Return the seconds needed to send the migration over the spare bandwidth."""
    spare = swap.free.bandwidth - expenditure.variation
    if spare <= 0:
        # Once migrated, the group's traffic alone would saturate the link: the state
        # never gets through in finite time, and even a stateless move would congest it.
        return math.inf
    return migration.total * 8 / (spare * 1e6)  # bytes over Mbit/s


def temporal_cost(swap: Swap) -> float:
    """Estimate the seconds a swap's migration takes, the replacement's worst downtime (Algorithm 5)."""
    migration = migration_cost(swap)
    return _seconds(swap, migration, _expenditure(swap, resource_usage(swap), migration))


def weighted_cost(swap: Swap) -> float:
    """Weigh a swap's expenditure against its migration time (Algorithm 6)."""
    # Algorithm 6 runs Algorithm 4 twice (once inside Algorithm 5); one run is the same.
    migration = migration_cost(swap)
    expenditure = _expenditure(swap, resource_usage(swap), migration)
    seconds = _seconds(swap, migration, expenditure)
    return _weigh(expenditure.expenditure, swap.weights.cost) + _weigh(seconds, swap.weights.time)


# Keyed by robotconfig.Heuristic; each gives the one comparable cost Algorithm 1 minimises.
HEURISTICS: dict[str, Callable[[Swap], float]] = {
    "resource_usage": lambda swap: resource_usage(swap).average,
    "migration_cost": lambda swap: migration_cost(swap).cost,
    "resource_expenditure": lambda swap: resource_expenditure(swap).expenditure,
    "temporal_cost": temporal_cost,
    "weighted_cost": weighted_cost,
}
