"""A rollout's health gate conditions over a Skill's metrics: `cpu < 0.8`, `metric:detections_per_s > 5` (pure).

The left side names a metric the cloud already stores for the robot: a robot resource (`cpu`,
`ram`, `bandwidth`, `battery`) or, after `metric:`, any metric a Skill's components report. A
gate passes when the metric's mean over the soak window meets the condition; a metric with no
point in the window fails its gate (a version that stops reporting is not healthy).
"""

from __future__ import annotations

import math
import operator
import re
from collections.abc import Callable, Iterable
from dataclasses import dataclass

from django.core.exceptions import ValidationError

RESOURCES = ("cpu", "ram", "bandwidth", "battery")
OPERATORS: dict[str, Callable[[float, float], bool]] = {
    "<=": operator.le,
    ">=": operator.ge,
    "==": operator.eq,
    "!=": operator.ne,
    "<": operator.lt,
    ">": operator.gt,
}
CONDITION = re.compile(
    r"^\s*(?P<name>metric:[A-Za-z_][A-Za-z0-9_.:-]{0,127}|[a-z]+)\s*(?P<op><=|>=|==|!=|<|>)\s*"
    r"(?P<value>[-+]?(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?)\s*$"
)
MAX_CONDITIONS = 32
# The share of its messages a Skill Router may drop over a soak before the robot fails its gate.
ROUTER_DROPPED_MAX = 0.05


@dataclass(frozen=True)
class Condition:
    """One gate condition: a metric's name, a comparison and a bound."""

    metric: str
    op: str
    bound: float

    def holds(self, values: Iterable[float]) -> bool:
        """Tell whether the mean of the window's values meets the condition (no values: it does not)."""
        points = [v for v in values if math.isfinite(v)]
        if not points:
            return False
        return OPERATORS[self.op](sum(points) / len(points), self.bound)

    def __str__(self) -> str:
        name = self.metric if self.metric in RESOURCES else f"metric:{self.metric}"
        return f"{name} {self.op} {self.bound:g}"


def parse_condition(text: object, field: str = "gates.conditions") -> Condition:
    """Read one condition; ValidationError naming the field and saying what a condition looks like."""
    found = CONDITION.match(text) if isinstance(text, str) else None
    if found is None:
        raise ValidationError(
            {field: [f"{text!r} is not a condition like 'cpu < 0.8' or 'metric:detections_per_s > 5'."]}
        )
    name = found["name"]
    if not name.startswith("metric:") and name not in RESOURCES:
        raise ValidationError(
            {field: [f"{name!r} is not a robot resource ({', '.join(RESOURCES)}); a Skill's metric is metric:<name>."]}
        )
    bound = float(found["value"])
    if not math.isfinite(bound):
        raise ValidationError({field: [f"{text!r}: the bound is not a finite number."]})
    return Condition(name.removeprefix("metric:"), found["op"], bound)


def parse_conditions(items: object, field: str = "gates.conditions") -> list[Condition]:
    """Read a gate's list of conditions; ValidationError naming the first bad one by its index."""
    if items is None:
        return []
    if not isinstance(items, list) or len(items) > MAX_CONDITIONS:
        raise ValidationError({field: [f"A list of at most {MAX_CONDITIONS} conditions."]})
    return [parse_condition(item, f"{field}[{index}]") for index, item in enumerate(items)]


def parse_share(value: object, field: str) -> float:
    """Read a share between 0 and 1; ValidationError naming the field."""
    if isinstance(value, bool) or not isinstance(value, int | float) or not 0 <= value <= 1:
        raise ValidationError({field: [f"{value!r} is not a share between 0 and 1 (0.05 is 5 %)."]})
    return float(value)


def router_dropped_share(delivered: Iterable[float], dropped: Iterable[float]) -> float | None:
    """Return the share of messages a router dropped, from its rates over a window (None: it routed nothing)."""
    delivered_mean, dropped_mean = _mean(delivered), _mean(dropped)
    routed = delivered_mean + dropped_mean
    return dropped_mean / routed if routed > 0 else None


def _mean(values: Iterable[float]) -> float:
    points = [v for v in values if math.isfinite(v)]
    return sum(points) / len(points) if points else 0.0
