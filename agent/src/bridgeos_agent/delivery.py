"""What each Skill Router delivers, as the rates the robot reports: the cloud's rollout gates read them.

A router counts, since it started, the messages it delivered to each topic's subscribers and
those it dropped (a slow peer's queue full), and its services' calls and errors
(``RouterStatistics.statistics``). Sampled with the robot's other readings, the difference
between two samples becomes two per-second rates of the Skill: delivered and dropped.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

ROUTER_DELIVERED = "router_delivered_per_s"
ROUTER_DROPPED = "router_dropped_per_s"

Reading = tuple[str, float, str | None, str | None]  # (name, value, skill, component)


def delivery_totals(statistics: Mapping[str, Mapping[str, Any]]) -> tuple[int, int]:
    """Return (delivered, dropped) over a router's topics and services since it started."""
    delivered = dropped = 0
    for figures in statistics.values():
        if figures.get("kind") == "topic":
            delivered += int(figures.get("delivered", 0))
            dropped += int(figures.get("dropped", 0))
        elif figures.get("kind") == "service":
            errors = int(figures.get("errors", 0))
            delivered += max(0, int(figures.get("calls", 0)) - errors)
            dropped += errors
    return delivered, dropped


class DeliveryRates:
    """Turn each Skill's router totals, sampled now and then, into delivered and dropped rates."""

    def __init__(self) -> None:
        # Skill -> (its router, delivered, dropped, when): a router started since is a new baseline.
        self._last: dict[str, tuple[object, int, int, float]] = {}

    def sample(self, routers: Iterable[tuple[str, Any]], now: float) -> list[Reading]:
        """Return the rates since the last sample of each (skill, router); a router's first sample has none."""
        readings: list[Reading] = []
        seen = set()
        for skill_id, router in routers:
            seen.add(skill_id)
            try:
                delivered, dropped = delivery_totals(router.statistics())
            except Exception:  # a router stopping as it is read: the next sample has it again
                continue
            last = self._last.get(skill_id)
            self._last[skill_id] = (router, delivered, dropped, now)
            if last is None or last[0] is not router or now <= last[3]:
                continue
            span = now - last[3]
            readings.append((ROUTER_DELIVERED, round(max(0, delivered - last[1]) / span, 3), skill_id, None))
            readings.append((ROUTER_DROPPED, round(max(0, dropped - last[2]) / span, 3), skill_id, None))
        for gone in set(self._last) - seen:
            del self._last[gone]
        return readings
