"""Decide per component whether to migrate (thesis Algorithms 8 and 9), learning from outcomes with a small MLP.

The Skill Manager calls :func:`decide_batch` once per decision interval with one
:class:`DecisionInput` per component. Everything here is plain data and arithmetic: the clock is a
float argument, there is no I/O and no asyncio. torch is imported lazily, on the first model built,
so the agent package still imports (and runs fixed-location or manual Skills) without it.

The estimate (the policy's cost functions) costs the location a component runs at from what is
measured there, but the other location only from what it declares and the robot's state: a
component that declares a tenth of the CPU it burns looks cheap on the robot every time it is in
the cloud. So each component owns a :class:`DecisionModel` that learns from outcomes: every
decision brings an :class:`Outcome`, the cost actually measured where the component runs and the
cost the estimate gives for that location from the other side; the network learns the difference
(the estimate's error) from the situation (:data:`FEATURES`), and a decision adds it to the
estimate of the cost at the target location (Algorithm 9's prediction). The network decides for a
location only once it beats the estimate on held-out outcomes: each outcome is predicted before the
network trains on it, and over the last ``TRUST_WINDOW`` outcomes at that location its mean error
must be at most ``TRUST_RATIO`` of the estimate's. Until then (and for a location where the
estimate is not wrong) the estimate decides, as in the thesis before training, but once the network
learns it does not move a component to a location for a gain smaller than what the latest outcomes
there showed it falls short by (every outcome is held out for an estimate, which never learns), plus
the reward's noise when that shortfall matters: an estimate that a few outcomes showed ten times too
low does not bring the component back every cooldown meanwhile.

Unlike the thesis, a move needs the reward to clear the threshold by a margin (hysteresis), in three
decisions running unless it clears it by ``noise_margin`` times the reward's recent noise, and none
may follow another within a cooldown: components do not flap when the reward is noisy, while a
real change, whose reward jumps far above the noise, moves at once. A move whose own outcome costs
past the noise more than it expected is undone within the cooldown. The noise is measured on the
reward relative to the level of its two costs and scaled to the current level, so the swings of a
busy robot's large costs do not hold back the next change at an idle robot's small ones.

The network itself and its batched training live in :mod:`bridgeos_agent.decisionmodel`.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from itertools import pairwise
from typing import Any, Literal

from bridgeos_agent.decisionmodel import (
    FEATURES,
    DecisionModel,
    Features,
    Side,
    predict_many,
    squash,
    train_many,
    unsquash,
)
from bridgeos_agent.skillconfig import Location, ManagerConfig

__all__ = [
    "FEATURES",
    "Decider",
    "Decision",
    "DecisionInput",
    "DecisionModel",
    "Features",
    "Outcome",
    "Side",
    "decide_and_learn",
    "decide_batch",
    "predict_many",
    "train_due",
    "train_many",
]

Mode = Literal["auto", "manual", "robot", "cloud"]
DecidedBy = Literal["rule", "estimate", "network"]


#: Held-out outcomes per location over which the network's and the estimate's errors are averaged.
TRUST_WINDOW = 6
#: Held-out outcomes at a location before the network may decide for it.
TRUST_MIN_SCORES = 3
#: The network decides for a location when its mean held-out error is at most this share of the estimate's.
# Three quarters: in a loaded offloading_quality run a network 38 off against the estimate's 62 (a tenfold
# misdeclaration) was kept out by one half; the right estimates' networks score 0.9 or more of theirs.
TRUST_RATIO = 0.75
#: Recent estimated rewards from which their noise is measured, and how many it takes to measure it.
NOISE_WINDOW = 20
NOISE_MIN_SAMPLES = 6
#: Decisions in a row whose reward must clear threshold + hysteresis when it is within the noise.
CONFIRMATIONS = 3
_AT_ROBOT, _AT_CLOUD = FEATURES.index("at_robot"), FEATURES.index("at_cloud")
#: median |X - Y| of two independent N(0, s) draws is 0.6745 * sqrt(2) * s: this turns it back into s.
_MEDIAN_DIFFERENCE_TO_SD = 1 / (0.6745 * math.sqrt(2))


@dataclass(frozen=True, slots=True)
class Outcome:
    """What running at its location actually cost a component, beside what the estimate said of it.

    realized: the policy's cost at ``location`` from what was measured there (CPU, RAM, traffic,
    latency, loss); estimated: the cost the estimate gives for ``location`` when the component is at
    the other one (declared resources); features: the situation as the network sees it from the
    other side, ``location`` being this one.
    """

    location: Side
    realized: float
    estimated: float
    features: Features

    @property
    def error(self) -> float:
        """Return how far the estimate from the other side was off (what the network learns)."""
        return self.realized - self.estimated


@dataclass(frozen=True, slots=True)
class DecisionInput:
    """Give the Decider what the Skill Manager knows about one component at one decision.

    location: where the component is active now; required_location: its Skill config location
    ("either" if movable); mode: the robot's offloading setting; resources_ok: the robot has
    free resources for it (only matters for a move to the robot); recommendation: a component's
    pushed recommendation (True migrate, False stay), which wins over everything but a fixed
    location and missing resources; estimated_reward: the policy's expected migration reward;
    outcome: what the last interval at its location measured, for the network to learn (None: nothing);
    moving: a move of the component is in flight, so its outcome is learnt and nothing is decided.
    """

    location: Side
    estimated_reward: float
    features: Features = field(default_factory=Features)
    required_location: Location = "either"
    mode: Mode = "auto"
    resources_ok: bool = True
    recommendation: bool | None = None
    outcome: Outcome | None = None
    moving: bool = False


@dataclass(frozen=True, slots=True)
class Decision:
    """Record one offloading decision: its inputs, the values compared and why, for the cloud's log."""

    component: str
    at: float
    location: Side
    target: Side
    migrate: bool
    reason: str
    mode: Mode
    estimated_reward: float
    prediction: float | None
    threshold: float
    hysteresis: float
    trained: bool
    samples_seen: int
    features: dict[str, float | str]
    # The held-out mean errors at the target location, of the network and of the estimate (see Decider.trust).
    network_error: float | None = None
    estimate_error: float | None = None
    trusted: bool = False  # whether the network's prediction decided
    margin: float | None = None  # the margin above the threshold that moved at once (see Decider.margin)
    decided_by: DecidedBy = "rule"  # what settled it: a rule (fixed, manual, ...), the estimate or the network

    def as_dict(self) -> dict[str, Any]:
        """Return the record as JSON-ready plain data."""
        return asdict(self)


class Decider:
    """Decide whether one component migrates (Algorithms 8 and 9) and learn from what each placement cost."""

    def __init__(
        self,
        component: str,
        config: ManagerConfig | None = None,
        *,
        model: DecisionModel | None = None,
        hysteresis: float | None = None,
        cooldown: float | None = None,
        noise_margin: float | None = None,
    ) -> None:
        self.component = component
        self.config = config or ManagerConfig()
        self.hysteresis = self.config.hysteresis if hysteresis is None else hysteresis
        self.cooldown = self.config.cooldown if cooldown is None else cooldown
        self.noise_margin = self.config.noise_margin if noise_margin is None else noise_margin
        for name in ("hysteresis", "cooldown", "noise_margin"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a finite number >= 0, not {value!r}")
        # The network's unit (see squash): costs within the decision margin stay linear, beyond it logarithmic.
        self.scale = max(abs(self.config.threshold) + self.hysteresis, 1e-6)
        self._model = model
        self.last_move: float | None = None
        # Where the last move went and what it expected the component to cost there.
        self._premise: tuple[Side, float] | None = None
        # Per location, the held-out (network error, estimate error) of the latest outcomes there, on the network's
        # scale.
        self._scores: dict[Side, deque[tuple[float, float]]] = {
            "robot": deque(maxlen=TRUST_WINDOW),
            "cloud": deque(maxlen=TRUST_WINDOW),
        }
        # Per location, the estimate's signed error on the latest outcomes there, every one of them: the estimate
        # never learns, so each outcome is held out for it, the first ones too (which no network has yet scored).
        self._misses: dict[Side, deque[float]] = {
            "robot": deque(maxlen=TRUST_WINDOW),
            "cloud": deque(maxlen=TRUST_WINDOW),
        }
        # The reward of running in the cloud rather than on the robot (so a move does not flip its sign), over
        # the level of the two costs it came from (see level): a relative difference of the costs, whose noise
        # does not grow with the costs, as a cost over a busy robot's little free CPU does.
        self._cloud_gains: deque[float] = deque(maxlen=NOISE_WINDOW)
        self._level = self.scale
        # Where the last decisions' rewards cleared threshold + hysteresis, and how many in a row.
        self._cleared: tuple[Side | None, int] = (None, 0)

    def level(self, features: Features) -> float:
        """Return the level of a decision's costs that its reward's noise is measured against."""
        # The decision's own scale keeps costs near zero from turning a small noise into a large share.
        return self.scale + (abs(features.cost_robot) + abs(features.cost_cloud)) / 2

    @property
    def reward_noise(self) -> float | None:
        """Return the standard deviation of the estimated reward's recent noise at the latest decision's level.

        Measured on the reward over its costs' level, then scaled to the latest level: after a busy robot, whose
        costs over its little free CPU swing by tens, an idle robot's small costs are not held to that noise.
        """
        # The median of successive differences: a real change is one large step, not noise.
        if len(self._cloud_gains) < NOISE_MIN_SAMPLES:
            return None
        steps = [abs(b - a) for a, b in pairwise(self._cloud_gains)]
        return statistics.median(steps) * _MEDIAN_DIFFERENCE_TO_SD * self._level

    @property
    def margin(self) -> float:
        """Return the margin above the threshold that moves at once (below it, CONFIRMATIONS in a row)."""
        # A real change jumps past noise_margin times the noise; a noisy stable reward does not.
        noise = self.reward_noise
        return self.hysteresis if noise is None else max(self.hysteresis, self.noise_margin * noise)

    def errors(self, location: Side) -> tuple[float | None, float | None]:
        """Return the network's and the estimate's mean held-out error at a location (None: none scored)."""
        scores = self._scores[location]
        if not scores:
            return None, None
        return sum(n for n, _ in scores) / len(scores), sum(e for _, e in scores) / len(scores)

    def underestimate(self, location: Side) -> float:
        """Return by how much the estimate fell short of the latest outcomes at a location, on average (0: not)."""
        misses = self._misses[location]
        return max(0.0, sum(misses) / len(misses)) if misses else 0.0

    def trust(self, location: Side) -> bool:
        """Tell whether the network decides for a location: trained and beating the estimate on held-out outcomes."""
        model = self._model
        if model is None or not model.trained or len(self._scores[location]) < TRUST_MIN_SCORES:
            return False
        network, estimate = self.errors(location)
        # Nothing beats an estimate that was never wrong (the cloud's, whose outcomes are the estimate's own).
        return network is not None and estimate is not None and estimate > 0 and network <= TRUST_RATIO * estimate

    @property
    def model(self) -> DecisionModel:
        """Return the component's network, built on first need so fixed components never load torch."""
        if self._model is None:
            self._model = DecisionModel(self.config.neural_network)
        return self._model

    def decide(self, decision_input: DecisionInput, now: float) -> Decision:
        """Decide for this component alone; see decide_batch."""
        return decide_batch([self], [decision_input], now)[0]

    def _precondition(self, given: DecisionInput, now: float) -> Decision | None:
        """Settle the decision without the network when a rule does, else return None."""
        target: Side = "cloud" if given.location == "robot" else "robot"
        if given.required_location != "either":
            return self._record(given, now, False, "fixed location", None)
        if target == "robot" and not given.resources_ok:
            return self._record(given, now, False, "no free resources on the robot", None)
        if given.recommendation is not None:
            return self._record(given, now, given.recommendation, "recommendation", None)
        if given.mode == "manual":
            return self._record(given, now, False, "manual offloading, no recommendation", None)
        if given.mode in ("robot", "cloud"):
            return self._record(given, now, target == given.mode, f"offloading fixed to {given.mode}", None)
        return None

    def queries(self, given: DecisionInput) -> list[list[float]]:
        """Return the network inputs of a decision: the target location's situation, then the outcome's."""
        target: Side = "cloud" if given.location == "robot" else "robot"
        # The features with the target's one-hot (dataclasses.replace costs 2000 components 30 ms a step).
        there = given.features.vector(self.scale)
        there[_AT_ROBOT], there[_AT_CLOUD] = (1.0, 0.0) if target == "robot" else (0.0, 1.0)
        vectors = [there]
        if given.outcome is not None:
            vectors.append(given.outcome.features.vector(self.scale))
        return vectors

    def doubt(self, estimated: float, shortfall: float) -> float:
        """Return, in cost units, how far above ``estimated`` lies a cost the estimate fell ``shortfall`` short of."""
        return unsquash(squash(estimated, self.scale) + shortfall, self.scale) - estimated

    def corrected(self, estimated: float, predicted: float) -> float:
        """Return the cost the network expects where the estimate says ``estimated``."""
        return unsquash(squash(estimated, self.scale) + predicted, self.scale)

    def _learn(self, outcome: Outcome, held_out: float | None) -> bool:
        """Score the network's held-out prediction of an outcome against the estimate, then record it."""
        target = squash(outcome.realized, self.scale) - squash(outcome.estimated, self.scale)
        self._misses[outcome.location].append(target)
        if held_out is not None and math.isfinite(held_out):
            # Scored on the network's own scale, where the estimate's error is ``target``: in cost units the
            # few outcomes of a robot turning busy (costs over its little free CPU, hundreds) would outweigh
            # every other, and a network right by a factor everywhere would look no better than the estimate.
            self._scores[outcome.location].append((abs(held_out - target), abs(target)))
        return self.model.record(outcome.features.vector(self.scale), target)

    def _conclude(self, given: DecisionInput, now: float, predicted: Sequence[float]) -> Decision:
        """Compare the reward (the network's where trusted, else the estimate) with the threshold.

        predicted: the network's outputs for :meth:`queries` (empty while it has never trained).
        """
        target: Side = "cloud" if given.location == "robot" else "robot"
        correction = None
        there = given.features.cost_cloud if target == "cloud" else given.features.cost_robot
        if predicted and math.isfinite(predicted[0]):
            correction = self.corrected(there, predicted[0]) - there
        # The network's reward: the estimated cost at the target corrected by what it learnt of outcomes there.
        prediction = None if correction is None else given.estimated_reward - correction
        trusted = prediction is not None and self.trust(target)
        reward = prediction if trusted and prediction is not None else given.estimated_reward
        source = "prediction" if trusted else "estimate"
        threshold = self.config.threshold
        # The noise is measured on earlier decisions: the reward that may be a real change is not yet in it.
        self._level = self.level(given.features)
        margin = self.margin
        gain = reward if given.location == "robot" else -reward
        self._cloud_gains.append(gain / self._level)
        clears = reward >= threshold + self.hysteresis
        at, run = self._cleared
        self._cleared = (given.location, run + 1 if at == given.location else 1) if clears else (None, 0)
        network, estimate = self.errors(target)
        # Only an estimate shown short of what the target costs argues against going there (a component that
        # burnt less than it declares, say starved on a busy machine, is no reason to stay away).
        # It is part of learning from outcomes: an estimate-only decider (a network that never trains) has no doubt.
        learning = self._model is not None and self._model.trained
        doubt = self.doubt(there, self.underestimate(target)) if learning and not trusted else 0.0
        cooling = self.last_move is not None and now - self.last_move < self.cooldown
        if not clears:
            migrate, reason = False, f"{source} below threshold + hysteresis"
        elif reward < threshold + doubt or (doubt > self.hysteresis and reward < threshold + doubt + margin):
            # The estimate was shown wrong at the target by more than this move gains (a component burning
            # more than it declares): it does not move the component there alone; the network, once trusted, may.
            # A doubt that matters is itself a guess from a few outcomes elsewhere (a busy robot's cost grows
            # faster than the estimate's): a gain within the reward's noise of it is no gain, however confirmed.
            migrate, reason = False, f"{source} above threshold + hysteresis but within its held-out error there"
        elif reward < threshold + margin and self._cleared[1] < CONFIRMATIONS:
            # Within the noise of a stable reward: one lucky draw does not move, a run of them does.
            migrate, reason = False, f"{source} above threshold + hysteresis but within the noise, unconfirmed"
        elif cooling and not self._refuted(given, reward, margin):
            migrate, reason = False, f"{source} above threshold, but cooling down after the last move"
        else:
            migrate, reason = True, f"{source} above threshold + hysteresis"
            if cooling:
                reason += ", the last move's outcome refuting it"
        if margin > self.hysteresis:
            reason += f" (noise margin {margin:.3g})"
        if doubt > self.hysteresis:
            reason += f" (estimate's doubt at the {target} {doubt:.3g})"
        if trusted:
            reason += f" (network beats the estimate at the {target}: held-out error {network:.3g} vs {estimate:.3g})"
        elif prediction is not None and network is not None and estimate is not None:
            reason += (
                f" (network not trusted at the {target}: held-out error {network:.3g} vs the estimate's {estimate:.3g})"
            )
        decision = self._record(
            given, now, migrate, reason, prediction, trusted, margin, "network" if trusted else "estimate"
        )
        if migrate:
            self._premise = (target, there + (correction if trusted and correction is not None else 0.0))
        return decision

    def _refuted(self, given: DecisionInput, reward: float, margin: float) -> bool:
        """Tell whether the last move was shown wrong: it costs here past the noise more than it expected.

        The cooldown keeps a noisy reward from moving a component back and forth; it does not keep a component
        where its first outcomes cost past the noise more than the move expected (an estimate that a component
        declaring a tenth of its CPU is cheap on a busy robot) until the cooldown ends.
        """
        if self._premise is None or self._premise[0] != given.location:
            return False
        here = given.features.cost_robot if given.location == "robot" else given.features.cost_cloud
        return here - self._premise[1] > margin and reward >= self.config.threshold + margin

    def _record(
        self,
        given: DecisionInput,
        now: float,
        migrate: bool,
        reason: str,
        prediction: float | None,
        trusted: bool = False,
        margin: float | None = None,
        decided_by: DecidedBy = "rule",
    ) -> Decision:
        """Build the decision record and remember a move for the cooldown."""
        if migrate:
            self.last_move = now
            self._premise = None  # what a rule's move expected is not known
        model = self._model
        target: Side = "cloud" if given.location == "robot" else "robot"
        network, estimate = self.errors(target)
        return Decision(
            component=self.component,
            at=now,
            location=given.location,
            target=target if migrate else given.location,
            migrate=migrate,
            reason=reason,
            mode=given.mode,
            estimated_reward=given.estimated_reward,
            prediction=prediction,
            threshold=self.config.threshold,
            hysteresis=self.hysteresis,
            trained=model is not None and model.trained,
            samples_seen=model.samples_seen if model is not None else 0,
            features=given.features.as_dict(),
            network_error=network,
            estimate_error=estimate,
            trusted=trusted,
            margin=margin,
            decided_by=decided_by,
        )


def decide_batch(deciders: Sequence[Decider], inputs: Sequence[DecisionInput], now: float) -> list[Decision]:
    """Decide for many components: one forward pass for all networks that have trained, one batched training step.

    Returns a decision for each input but those of components in the middle of a move (``moving``).
    """
    decisions, due = decide_and_learn(deciders, inputs, now)
    train_due(due)
    return decisions


def decide_and_learn(
    deciders: Sequence[Decider], inputs: Sequence[DecisionInput], now: float
) -> tuple[list[Decision], list[DecisionModel]]:
    """Decide as :func:`decide_batch` does, but return the networks due a training step rather than train them.

    The Skill Manager starts the moves first and trains (:func:`train_due`) off its event loop meanwhile.
    """
    if len(deciders) != len(inputs):
        raise ValueError("one input per decider")
    deciding = [not given.moving for given in inputs]
    decisions: list[Decision | None] = [
        d._precondition(given, now) if decide else None
        for d, given, decide in zip(deciders, inputs, deciding, strict=True)
    ]
    # Every outcome is learnt, whoever decides (a manual mode or a recommendation included), and while a
    # move is in flight: the copy it leaves still runs, and its seconds of outcomes are what the network
    # needs before it may decide where the component goes next.
    learners = [
        i for i, decision in enumerate(decisions) if (decision is None and deciding[i]) or inputs[i].outcome is not None
    ]
    # A network still warming up (fewer than trained_after samples) may not decide: neither asked nor
    # scored, so 2000 warming-up components cost no inference.
    asked = [i for i in learners if deciders[i].model.trained]
    queries = {i: deciders[i].queries(inputs[i]) for i in asked}
    models = [deciders[i].model for i in asked for _ in queries[i]]
    values = predict_many(models, [v for i in asked for v in queries[i]]) if models else []
    predicted: dict[int, list[float]] = {}
    position = 0
    for i in asked:
        predicted[i] = values[position : position + len(queries[i])]
        position += len(queries[i])
    due: list[DecisionModel] = []
    for i in learners:
        decider, given, outputs = deciders[i], inputs[i], predicted.get(i, [])
        # Learnt before deciding: the trust gate counts this outcome's held-out score.
        if given.outcome is not None and decider._learn(given.outcome, outputs[1] if len(outputs) > 1 else None):
            due.append(decider.model)
        if decisions[i] is None and deciding[i]:
            decisions[i] = decider._conclude(given, now, outputs)
    return [d for d in decisions if d is not None], due


def train_due(due: Sequence[DecisionModel]) -> None:
    """Train the networks :func:`decide_and_learn` found due, each its own number of steps (one batch per round)."""
    for round_ in range(max((m.config.train_steps for m in due), default=0)):
        train_many([m for m in due if m.config.train_steps > round_])
