"""Decide the robot's cloud role takeover (thesis Algorithm 7) without doing any of it.

Pure: ``CloudMonitor`` turns connection events, stamped with a caller-given time, into
"takeover" and "revert" transitions; ``plan_takeover`` picks what to launch on the robot
and ``plan_revert`` what to stop afterwards. The controller sends the messages, launches
and stops the containers.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Literal

from bridgeos_agent.allocation import ComponentSnapshot
from bridgeos_agent.heuristics import ZERO, Resources

__all__ = ["CloudMonitor", "Transition", "plan_revert", "plan_takeover"]

Transition = Literal["takeover", "revert"]


def plan_takeover(skills: Mapping[str, Mapping[str, ComponentSnapshot]], free: Resources) -> dict[str, list[str]]:
    """Pick, per Skill, the cloud components to launch on the robot while the cloud is lost."""
    plan: dict[str, list[str]] = {}
    for skill_id, components in skills.items():
        taken: list[str] = []
        needed = ZERO
        for component_id, component in components.items():
            # Only what runs in the cloud needs taking over; a component running nowhere
            # was stopped on purpose and stays stopped.
            if component.active_location != "cloud":
                continue
            if component.required_location == "cloud":
                # The Skill stays broken without this component, so launching the rest
                # would spend resources for nothing. (The thesis's "exit for" would still
                # launch whatever came before it in the loop.)
                taken = []
                break
            taken.append(component_id)
            needed += component.required
        if taken and needed.fits(free):
            plan[skill_id] = taken
            # The thesis checks every Skill against the same free resources, so two Skills
            # could each claim the same headroom; taking it away first prevents overcommit.
            free -= needed
    return plan


def plan_revert(migrations: Mapping[str, Sequence[str]]) -> list[tuple[str, str]]:
    """List the (skill, component) duplicates to stop once the cloud is back."""
    return [(skill_id, component_id) for skill_id, taken in migrations.items() for component_id in taken]


class CloudMonitor:
    """Turn cloud connection events into takeover and revert transitions, each once."""

    def __init__(self, disconnection_delay: float, now: float) -> None:
        if not (disconnection_delay > 0 and math.isfinite(disconnection_delay)):
            raise ValueError(f"disconnection_delay must be a positive number of seconds, not {disconnection_delay!r}")
        self.disconnection_delay = disconnection_delay
        # Starting counts as contact: a robot that never reaches the cloud still takes
        # over the components it re-adopted after a restart, once the delay has passed.
        self._last_seen = now
        self._taken_over = False

    @property
    def taken_over(self) -> bool:
        """Tell whether the robot currently stands in for the cloud."""
        return self._taken_over

    @property
    def last_seen(self) -> float:
        """Return when the cloud was last heard from."""
        return self._last_seen

    def on_message(self, now: float) -> Transition | None:
        """Record that the cloud spoke; hand its role back if the robot had taken it."""
        self._last_seen = max(self._last_seen, now)
        if self._taken_over:
            self._taken_over = False
            return "revert"
        return None

    def on_disconnect(self, now: float) -> Transition | None:
        """Record that the connection closed; take over if the cloud has been silent long enough."""
        # A closed socket counts from the last message, not from the close (Algorithm 7,
        # line 6), so a quick reconnect does not disturb the Skills.
        return self.tick(now)

    def tick(self, now: float) -> Transition | None:
        """Take over once the cloud has been silent for the disconnection delay."""
        # Silence alone is enough, open socket or not: the thesis lists NoResponse with the
        # closed and lost connections, and connection_lost_after is "seconds of silence".
        if not self._taken_over and now - self._last_seen >= self.disconnection_delay:
            self._taken_over = True
            return "takeover"
        return None
