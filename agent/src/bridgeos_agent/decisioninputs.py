"""What the Skill Manager measured, as a decision's inputs, and a carried-out move, as an event.

Pure functions over plain data (no host, no clock): a component's averaged usage, the share of
a capacity still free, the outcome a decision module learns from where a component runs
(``observed_outcome``), and the ``offloading_decision`` event of a move (``decision_event``).
"""

from __future__ import annotations

import dataclasses
import math
from collections import deque
from typing import Any

from bridgeos_agent.decision import Decision, Features, Outcome, Side
from bridgeos_agent.heuristics import Resources
from bridgeos_agent.policies import Metrics, PolicyCosts, PolicyEstimator

__all__ = ["Usage", "decision_event", "finite", "free_share", "means", "observed_outcome", "optional_finite"]


@dataclasses.dataclass(frozen=True, slots=True)
class Usage:
    """A component's averaged CPU (cores) and RAM (MiB)."""

    cpu: float
    ram: float


def means(window: deque[tuple[float, float]]) -> tuple[float, float]:
    """Return the mean CPU and RAM of a window of measurements."""
    return sum(c for c, _ in window) / len(window), sum(r for _, r in window) / len(window)


def free_share(free: float | None, capacity: float) -> float:
    """Return the free share of a capacity in [0, 1]; unknown counts as all free."""
    if free is None or capacity <= 0:
        return 1.0
    return max(0.0, min(1.0, free / capacity))


def observed_outcome(
    estimator: PolicyEstimator,
    policy: str,
    ros: bool,
    location: Side,
    estimate: PolicyCosts,
    needs: Resources,
    measured: Any,
    metrics: Metrics,
    features: Features,
    capacity: Resources,
) -> Outcome | None:
    """Return what running where it runs cost a component, beside what the estimate says of it from elsewhere.

    The cost where it runs is the estimate's own, from what was measured there. On the robot the
    runtime measures its CPU and RAM: from the cloud the estimate would cost the robot with the
    declared ones instead, and that difference is what the network learns. In the cloud nothing
    more is measured than the estimate uses, so the outcome there is the estimate (error 0).
    """
    if location == "cloud":
        return Outcome("cloud", estimate.cost_cloud, estimate.cost_cloud, features)
    if measured is None:
        return None  # no measurement yet (just moved here): nothing happened that the estimate did not assume
    # The robot as the estimate sees it from the cloud: free what the component uses, take what it declares.
    elsewhere = dataclasses.replace(
        metrics,
        cpu_free=max(0.0, metrics.cpu_free + measured.cpu - needs.cpu),
        ram_free=max(0.0, metrics.ram_free + measured.ram - needs.ram),
    )
    try:
        seen = estimator.cost(policy, "robot", needs, elsewhere, ros)
    except ValueError:
        return None
    # Built directly, not by dataclasses.replace: half of 2000 components on the robot, every decision.
    view = Features(
        cpu_available=free_share(metrics.cpu_free + measured.cpu, capacity.cpu),
        ram_available=free_share(metrics.ram_free + measured.ram, capacity.ram),
        bandwidth_available=features.bandwidth_available,
        latency=features.latency,
        loss=features.loss,
        battery=features.battery,
        location="robot",
        cost_robot=seen,
        cost_cloud=estimate.cost_cloud,
    )
    return Outcome("robot", estimate.cost_robot, seen, view)


def decision_event(
    decision: Decision,
    estimate: PolicyCosts,
    decided_at: float,
    duration_s: float,
    error: str | None,
    skill_id: str,
) -> dict[str, Any]:
    """Describe a carried-out move as the data of an ``offloading_decision`` event."""
    inputs = {
        key: (value if isinstance(value, str) else float(value))
        for key, value in decision.features.items()
        if isinstance(value, str) or math.isfinite(value)
    }
    prediction = decision.prediction
    data: dict[str, Any] = {
        "skill": skill_id,
        "component": decision.component,
        "location": decision.location,
        "target": decision.target,
        "outcome": "failed" if error else "moved",
        "reason": decision.reason[:1000],
        "policy": estimate.policy,
        "cost_robot": finite(estimate.cost_robot),
        "cost_cloud": finite(estimate.cost_cloud),
        "estimated_reward": finite(decision.estimated_reward),
        "prediction": prediction if prediction is not None and math.isfinite(prediction) else None,
        "threshold": float(decision.threshold),
        "hysteresis": float(decision.hysteresis),
        "trained": decision.trained,
        "samples_seen": decision.samples_seen,
        "inputs": inputs,
        "decided_by": decision.decided_by,
        "network_error": optional_finite(decision.network_error),
        "estimate_error": optional_finite(decision.estimate_error),
        "decided_at": decided_at,
        "duration_s": max(0.0, duration_s),
    }
    if error:
        data["error"] = error[:2000]
    return data


def finite(value: float) -> float:
    """Return a float the protocol accepts: an infinite cost is clamped to the largest float."""
    value = float(value)
    if math.isnan(value):
        return 0.0
    return max(-1.7e308, min(1.7e308, value))


def optional_finite(value: float | None) -> float | None:
    """Return a finite float or None, as the protocol's optional figures."""
    return float(value) if value is not None and math.isfinite(value) else None
