"""How a rollout walks a fleet: its batches, how many robots change at once, and when it stops (pure).

A rollout first touches a canary batch (a count or a share of the robots), then batches that
grow by a factor (exponential, as Greengrass's rollout rate) or stay the same size (fixed).
Within a batch at most ``max_unavailable`` robots install or verify at once. It stops when the
failed share of the robots it finished passes ``failure_threshold_pct``, but only once at least
``min_robots`` have finished (Greengrass's abort rule), so one early failure in a large fleet
is judged against enough robots.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass
from typing import Any

from django.core.exceptions import ValidationError

GROWTHS = ("exponential", "fixed")
ON_FAILURE = ("rollback", "pause")
COUNT_OR_SHARE = re.compile(r"^(?P<number>\d+(?:\.\d+)?)(?P<percent>%?)$")
MAX_PAUSE_S = 7 * 24 * 3600


@dataclass(frozen=True)
class Share:
    """A number of robots, written as a count (3) or a share of the fleet (10%)."""

    value: float
    percent: bool

    def of(self, total: int) -> int:
        """Return how many robots of ``total`` this is: a share rounds up, and never to zero of a fleet."""
        if not self.percent:
            return min(int(self.value), total)
        return min(total, max(1 if total else 0, math.ceil(total * self.value / 100)))

    def __str__(self) -> str:
        return f"{self.value:g}%" if self.percent else str(int(self.value))


@dataclass(frozen=True)
class Strategy:
    """The shape of a rollout: canary, growth, pause between batches, and the abort rule."""

    first: Share = Share(1, False)
    growth: str = "exponential"
    factor: float = 2.0
    # Seconds between batches; None waits for an operator to resume.
    pause_s: float | None = 0.0
    max_unavailable: Share = Share(100, True)
    soak_s: float = 60.0
    failure_threshold_pct: float = 0.0
    min_robots: int = 1
    on_failure: str = "rollback"

    def batches(self, total: int) -> list[int]:
        """Return the size of each batch for a fleet of ``total`` robots, in order; their sum is ``total``."""
        sizes: list[int] = []
        size, left = self.first.of(total), total
        while left > 0:
            step = max(1, min(size, left))
            sizes.append(step)
            left -= step
            if self.growth == "exponential":
                size = max(size + 1, math.ceil(size * self.factor))
        return sizes

    def at_once(self, batch: int) -> int:
        """Return how many robots of a batch may install or verify at the same time."""
        return max(1, self.max_unavailable.of(batch))

    def should_stop(self, finished: int, failed: int) -> bool:
        """Tell whether the failures so far stop the rollout: past the threshold, once enough robots finished."""
        if failed == 0 or finished < self.min_robots:
            return False
        return 100 * failed / finished > self.failure_threshold_pct


def share(value: Any, field: str) -> Share:
    """Read a count (3) or a share ("10%") of robots; ValidationError naming the field otherwise."""
    text = str(value).strip() if isinstance(value, int | float | str) and not isinstance(value, bool) else ""
    found = COUNT_OR_SHARE.match(text)
    if found is None:
        raise ValidationError({field: [f"{value!r} is neither a count of robots (3) nor a share of them (10%)."]})
    number, percent = float(found["number"]), bool(found["percent"])
    if number <= 0 or (percent and number > 100) or (not percent and number != int(number)):
        raise ValidationError({field: [f"{value!r}: a count is a whole number >= 1, a share is in (0, 100]%."]})
    return Share(number, percent)


def parse_strategy(data: Any, *, prefix: str = "strategy") -> Strategy:
    """Read a rollout's strategy from JSON; every bad value is a ValidationError naming its field."""
    if data is None:
        return Strategy()
    if not isinstance(data, dict):
        raise ValidationError({prefix: ["The strategy is a JSON object."]})
    known = {
        "first",
        "growth",
        "factor",
        "pause_s",
        "max_unavailable",
        "soak_s",
        "failure_threshold_pct",
        "min_robots",
        "on_failure",
    }
    unknown = sorted(set(data) - known)
    if unknown:
        raise ValidationError({f"{prefix}.{unknown[0]}": [f"Unknown; a strategy has {', '.join(sorted(known))}."]})
    default = Strategy()
    growth = data.get("growth", default.growth)
    if growth not in GROWTHS:
        raise ValidationError({f"{prefix}.growth": [f"{growth!r} is not one of {', '.join(GROWTHS)}."]})
    on_failure = data.get("on_failure", default.on_failure)
    if on_failure not in ON_FAILURE:
        raise ValidationError({f"{prefix}.on_failure": [f"{on_failure!r} is not one of {', '.join(ON_FAILURE)}."]})
    pause = data.get("pause_s", default.pause_s)
    return Strategy(
        first=share(data["first"], f"{prefix}.first") if "first" in data else default.first,
        growth=growth,
        factor=_number(data, "factor", default.factor, prefix, low=1.0, high=100.0, low_open=True),
        pause_s=None if pause is None else _number(data, "pause_s", 0.0, prefix, low=0.0, high=MAX_PAUSE_S),
        max_unavailable=(
            share(data["max_unavailable"], f"{prefix}.max_unavailable")
            if "max_unavailable" in data
            else default.max_unavailable
        ),
        soak_s=_number(data, "soak_s", default.soak_s, prefix, low=0.0, high=MAX_PAUSE_S),
        failure_threshold_pct=_number(data, "failure_threshold_pct", 0.0, prefix, low=0.0, high=100.0),
        min_robots=int(_number(data, "min_robots", 1, prefix, low=1, high=1_000_000, whole=True)),
        on_failure=on_failure,
    )


def _number(
    data: dict[str, Any],
    key: str,
    default: float,
    prefix: str,
    *,
    low: float,
    high: float,
    low_open: bool = False,
    whole: bool = False,
) -> float:
    """Read one number of the strategy within its bounds; ValidationError naming it otherwise."""
    value = data.get(key, default)
    field = f"{prefix}.{key}"
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ValidationError({field: [f"{value!r} is not a number."]})
    if whole and value != int(value):
        raise ValidationError({field: [f"{value!r} is not a whole number."]})
    if value < low or value > high or (low_open and value == low):
        bound = f"above {low:g}" if low_open else f"at least {low:g}"
        raise ValidationError({field: [f"{value!r} is out of range: {bound} and at most {high:g}."]})
    return float(value)
