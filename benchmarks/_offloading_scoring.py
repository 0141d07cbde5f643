"""offloading_quality's scoring: what a run recorded, costed against every static placement and the oracle."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

from _offloading_scenario import ADAPTED_WITHIN, CPU_CORES, FLAP_WINDOW, ROBOT_CONFIG, SETTLE_S, Phase, Script

from bridgeos_agent.heuristics import Resources
from bridgeos_agent.policies import Metrics, PolicyEstimator
from bridgeos_agent.robotconfig import parse_robot_config
from bridgeos_agent.skillconfig import SkillConfig

# --------------------------------------------------------------------------- costing placements


class Costing:
    """Cost a placement under given conditions with the Skill's own policy (noiseless, declared usage)."""

    def __init__(self, config: SkillConfig) -> None:
        robot = parse_robot_config(ROBOT_CONFIG)
        self.estimator = PolicyEstimator.of(robot, config.manager, Resources.of(robot.resources))
        self.usage = {name: Resources.of(c.resources) for name, c in config.components.items()}
        self.names = list(config.components)
        self.baseline = 0.05 * CPU_CORES  # SimulatedRobot's own idle load
        self._cache: dict[tuple[tuple[str, ...], Phase], float] = {}

    def rate(self, placement: tuple[str, ...], phase: Phase) -> float:
        """Return the summed cost per second of the components placed so, under a phase's conditions."""
        key = (placement, phase)
        if key not in self._cache:
            on_robot = sum(
                self.usage[n].cpu for n, where in zip(self.names, placement, strict=True) if where == "robot"
            )
            free = max(0.0, CPU_CORES - self.baseline - phase.load - on_robot)
            state = Metrics(cpu_free=free, ram_free=4096.0, bandwidth_available=phase.link)
            self._cache[key] = sum(
                self.estimator.cost("custom", where, self.usage[name], state)
                for name, where in zip(self.names, placement, strict=True)
            )
        return self._cache[key]

    def placements(self) -> list[tuple[str, ...]]:
        """Return every static placement of the Skill's components."""
        return list(itertools.product(("robot", "cloud"), repeat=len(self.names)))


@dataclass
class Run:
    """What the run recorded: placements over time (seconds since the script started) and every move."""

    timeline: list[tuple[float, tuple[str, ...]]] = field(default_factory=list)
    moves: list[tuple[float, str, str, str]] = field(default_factory=list)  # t, component, from, to
    rewards: dict[str, dict[float, tuple[float, float]]] = field(default_factory=dict)  # name -> at -> (t, reward)
    decisions: int = 0
    trusted: int = 0
    trained: int = 0
    decided_by: dict[tuple[str, float], str] = field(default_factory=dict)  # (name, at) -> rule/estimate/network
    # name -> the network's and the estimate's mean held-out error on the robot at the end
    robot_errors: dict[str, tuple[float | None, float | None]] = field(default_factory=dict)

    @property
    def learned_share(self) -> float:
        """Return the share of the adaptive decisions (not settled by a rule) the network took."""
        adaptive = [by for by in self.decided_by.values() if by != "rule"]
        return sum(by == "network" for by in adaptive) / len(adaptive) if adaptive else 0.0


def integrate(run: Run, script: Script, costing: Costing) -> tuple[float, list[float]]:
    """Return the adaptive run's total cost and its cost per phase."""
    per_phase = [0.0] * len(script.phases)
    for (t, placement), (t_next, _) in itertools.pairwise([*run.timeline, (script.duration, ())]):
        index = script.index(t)
        per_phase[index] += costing.rate(placement, script.phases[index]) * (min(t_next, script.duration) - t)
    return sum(per_phase), per_phase


def adaptation(run: Run, script: Script, costing: Costing, best: list[tuple[str, ...]]) -> list[dict]:
    """Return, for each change (the start included), how long the run took to be within 5 % of the best."""
    results = []
    for index, phase in enumerate(script.phases):
        start, end = script.bounds(index)
        target = costing.rate(best[index], phase) * ADAPTED_WITHIN
        adapted = exact = None
        for t, placement in run.timeline:
            if start <= t < end:
                if adapted is None and costing.rate(placement, phase) <= target:
                    adapted = t - start
                if exact is None and placement == best[index]:
                    exact = t - start
        results.append({"phase": index + 1, "adapt_s": adapted, "exact_s": exact})
    return results


def flaps(run: Run, script: Script) -> list[tuple[float, str]]:
    """Return the moves undone within FLAP_WINDOW seconds with no change of conditions in between."""
    found = []
    last: dict[str, tuple[float, str, str]] = {}
    for t, name, before, after in run.moves:
        previous = last.get(name)
        if (
            previous is not None
            and previous[1] == after
            and previous[2] == before
            and t - previous[0] <= FLAP_WINDOW
            and script.index(previous[0]) == script.index(t)
        ):
            found.append((t, name))
        last[name] = (t, before, after)
    return found


def stable_moves(run: Run, script: Script) -> list[tuple[float, str]]:
    """Return the moves made in the stable phase after its first SETTLE_S seconds (none with no stable phase)."""
    if not script.stable_s:
        return []
    start, end = script.bounds(len(script.phases) - 1)
    return [(t, name) for t, name, _, _ in run.moves if start + SETTLE_S <= t < end]


def reward_noise(run: Run, script: Script) -> dict[str, float]:
    """Return each component's estimated-reward standard deviation in the stable phase after SETTLE_S."""
    start, end = script.bounds(len(script.phases) - 1)
    noise = {}
    for name, decided in run.rewards.items():
        values = [reward for t, reward in decided.values() if start + SETTLE_S <= t < end]
        if len(values) > 1:
            mean = sum(values) / len(values)
            noise[name] = math.sqrt(sum((v - mean) ** 2 for v in values) / (len(values) - 1))
    return noise


def over_oracle(run: Run, script: Script, costing: Costing) -> float:
    """Return a run's cost over the hindsight oracle's in the changing phases."""
    _, per_phase = integrate(run, script, costing)
    changes = range(script.changing)
    best = [min(costing.placements(), key=lambda p, ph=phase: costing.rate(p, ph)) for phase in script.phases]
    oracle = sum(costing.rate(best[i], script.phases[i]) * script.phase_s for i in changes)
    return sum(per_phase[i] for i in changes) / oracle
