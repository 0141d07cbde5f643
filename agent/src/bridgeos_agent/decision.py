"""Decide per component whether to migrate (thesis Algorithms 8 and 9), with a small MLP per component.

The Skill Manager calls :func:`decide_batch` once per decision interval with one
:class:`DecisionInput` per component. Everything here is plain data and arithmetic: the clock is a
float argument, there is no I/O and no asyncio. torch is imported lazily, on the first model built,
so the agent package still imports (and runs fixed-location or manual Skills) without it.

Each component owns a :class:`DecisionModel`: an MLP shaped by ``NeuralNetworkConfig`` mapping a
fixed-length feature vector (:data:`FEATURES`) to the predicted migration reward. Until it has seen
``trained_after`` samples the :class:`Decider` decides by the estimated reward (from the policy cost
functions), records every decision as a sample and trains every ``warmup_train_every`` of them;
afterwards it decides by the model's prediction and retrains every ``train_every`` decisions
(Algorithm 9). Unlike the thesis, a move needs the reward to clear the threshold by a margin
(hysteresis), in three decisions running unless it clears it by ``noise_margin`` times the reward's
recent noise, and none may follow another within a cooldown: components do not flap when the
reward is noisy, while a real change, whose reward jumps far above the noise, moves at once; and a
trained network decides only while its recent error against the estimate stays within the
hysteresis margin (an under-trained network that never moves anything costs more than the estimate
it learns from).

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

from bridgeos_agent.decisionmodel import FEATURES, DecisionModel, Features, Side, predict_many, train_many
from bridgeos_agent.skillconfig import Location, ManagerConfig

__all__ = [
    "FEATURES",
    "Decider",
    "Decision",
    "DecisionInput",
    "DecisionModel",
    "Features",
    "Side",
    "decide_batch",
    "predict_many",
    "train_many",
]

Mode = Literal["auto", "manual", "robot", "cloud"]


#: Decisions over which a trained network's error against the estimate is averaged (the trust gate).
TRUST_WINDOW = 5
#: Recent estimated rewards from which their noise is measured, and how many it takes to measure it.
NOISE_WINDOW = 20
NOISE_MIN_SAMPLES = 6
#: Decisions in a row whose reward must clear threshold + hysteresis when it is within the noise.
CONFIRMATIONS = 3
#: median |X - Y| of two independent N(0, s) draws is 0.6745 * sqrt(2) * s: this turns it back into s.
_MEDIAN_DIFFERENCE_TO_SD = 1 / (0.6745 * math.sqrt(2))


@dataclass(frozen=True, slots=True)
class DecisionInput:
    """Give the Decider what the Skill Manager knows about one component at one decision.

    location: where the component is active now; required_location: its Skill config location
    ("either" if movable); mode: the robot's offloading setting; resources_ok: the robot has
    free resources for it (only matters for a move to the robot); recommendation: a component's
    pushed recommendation (True migrate, False stay), which wins over everything but a fixed
    location and missing resources; estimated_reward: the policy's expected migration reward.
    """

    location: Side
    estimated_reward: float
    features: Features = field(default_factory=Features)
    required_location: Location = "either"
    mode: Mode = "auto"
    resources_ok: bool = True
    recommendation: bool | None = None


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
    network_error: float | None = None  # the network's recent mean error against the estimate
    trusted: bool = False  # whether the network's prediction decided
    margin: float | None = None  # the margin above the threshold that moved at once (see Decider.margin)

    def as_dict(self) -> dict[str, Any]:
        """Return the record as JSON-ready plain data."""
        return asdict(self)


class Decider:
    """Decide whether one component migrates (Algorithms 8 and 9) and learn from each decision."""

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
        self._model = model
        self.last_move: float | None = None
        self._errors: deque[float] = deque(maxlen=TRUST_WINDOW)
        # The reward of running in the cloud rather than on the robot, so a move does not flip its sign.
        self._cloud_gains: deque[float] = deque(maxlen=NOISE_WINDOW)
        # Where the last decisions' rewards cleared threshold + hysteresis, and how many in a row.
        self._cleared: tuple[Side | None, int] = (None, 0)

    @property
    def reward_noise(self) -> float | None:
        """Return the standard deviation of the estimated reward's recent noise (None until measured)."""
        # The median of successive differences: a real change is one large step, not noise.
        if len(self._cloud_gains) < NOISE_MIN_SAMPLES:
            return None
        steps = [abs(b - a) for a, b in pairwise(self._cloud_gains)]
        return statistics.median(steps) * _MEDIAN_DIFFERENCE_TO_SD

    @property
    def margin(self) -> float:
        """Return the margin above the threshold that moves at once (below it, CONFIRMATIONS in a row)."""
        # A real change jumps past noise_margin times the noise; a noisy stable reward does not.
        noise = self.reward_noise
        return self.hysteresis if noise is None else max(self.hysteresis, self.noise_margin * noise)

    @property
    def network_error(self) -> float | None:
        """Return the trained network's mean absolute error against the estimate over recent decisions."""
        return sum(self._errors) / len(self._errors) if self._errors else None

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

    def _conclude(self, given: DecisionInput, now: float, prediction: float | None) -> tuple[Decision, bool]:
        """Compare the reward with the threshold, record the sample; return the decision and whether training is due."""
        usable = prediction is not None and math.isfinite(prediction)
        trusted = False
        if prediction is not None and usable:
            # The trust gate: a network that strays from the policy it learns from does not decide.
            self._errors.append(abs(prediction - given.estimated_reward))
            error = self.network_error
            trusted = error is not None and error <= self.hysteresis
        reward = prediction if trusted and prediction is not None else given.estimated_reward
        source = "prediction" if trusted else "estimate"
        threshold = self.config.threshold
        # The noise is measured on earlier decisions: the reward that may be a real change is not yet in it.
        margin = self.margin
        self._cloud_gains.append(given.estimated_reward if given.location == "robot" else -given.estimated_reward)
        clears = reward >= threshold + self.hysteresis
        at, run = self._cleared
        self._cleared = (given.location, run + 1 if at == given.location else 1) if clears else (None, 0)
        if not clears:
            migrate, reason = False, f"{source} below threshold + hysteresis"
        elif reward < threshold + margin and self._cleared[1] < CONFIRMATIONS:
            # Within the noise of a stable reward: one lucky draw does not move, a run of them does.
            migrate, reason = False, f"{source} above threshold + hysteresis but within the noise, unconfirmed"
        elif self.last_move is not None and now - self.last_move < self.cooldown:
            migrate, reason = False, f"{source} above threshold, but cooling down after the last move"
        else:
            migrate, reason = True, f"{source} above threshold + hysteresis"
        if margin > self.hysteresis:
            reason += f" (noise margin {margin:.3g})"
        if usable and not trusted:
            reason += f" (network error {self.network_error:.3g} exceeds the hysteresis)"
        due = self.model.record(given.features.vector(), given.estimated_reward)
        return self._record(given, now, migrate, reason, prediction, trusted, margin), due

    def _record(
        self,
        given: DecisionInput,
        now: float,
        migrate: bool,
        reason: str,
        prediction: float | None,
        trusted: bool = False,
        margin: float | None = None,
    ) -> Decision:
        """Build the decision record and remember a move for the cooldown."""
        if migrate:
            self.last_move = now
        model = self._model
        return Decision(
            component=self.component,
            at=now,
            location=given.location,
            target=("cloud" if given.location == "robot" else "robot") if migrate else given.location,
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
            network_error=self.network_error if prediction is not None else None,
            trusted=trusted,
            margin=margin,
        )


def decide_batch(deciders: Sequence[Decider], inputs: Sequence[DecisionInput], now: float) -> list[Decision]:
    """Decide for many components: one forward pass for all trained networks, one batched training step."""
    if len(deciders) != len(inputs):
        raise ValueError("one input per decider")
    decisions: list[Decision | None] = [d._precondition(given, now) for d, given in zip(deciders, inputs, strict=True)]
    adaptive = [i for i, decision in enumerate(decisions) if decision is None]
    trained = [i for i in adaptive if deciders[i].model.trained]
    predictions: dict[int, float] = {}
    if trained:
        values = predict_many([deciders[i].model for i in trained], [inputs[i].features.vector() for i in trained])
        predictions = dict(zip(trained, values, strict=True))
    due: list[DecisionModel] = []
    for i in adaptive:
        decision, train = deciders[i]._conclude(inputs[i], now, predictions.get(i))
        decisions[i] = decision
        if train:
            due.append(deciders[i].model)
    if due:
        train_many(due)
    return [d for d in decisions if d is not None]
