"""The decision network of a component: its inputs (:class:`Features`) and a batched torch MLP that learns outcomes.

Split from :mod:`bridgeos_agent.decision`, which decides with it (Algorithms 8 and 9). All models
of one shape are evaluated together: one batched matmul per layer for inference and one batched
forward/backward with an elementwise Adam for training, so 2000 components cost about as many
torch calls as one. torch is imported lazily, on the first model built.
"""

from __future__ import annotations

import io
import math
import os
from array import array
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import pairwise
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from bridgeos_agent.skillconfig import NeuralNetworkConfig

if TYPE_CHECKING:
    from torch import Tensor

__all__ = ["FEATURES", "DecisionModel", "Features", "Side", "predict_many", "squash", "train_many", "unsquash"]

Side = Literal["robot", "cloud"]
OptimizerName = Literal["adam", "sgd"]

#: Names of the model's inputs, in order (see :class:`Features`).
FEATURES: tuple[str, ...] = (
    "cpu_available",
    "ram_available",
    "bandwidth_available",
    "latency",
    "loss",
    "battery",
    "at_robot",
    "at_cloud",
    "cost_robot",
    "cost_cloud",
)
N_FEATURES = len(FEATURES)
#: What the network learns, saved with it: a network saved by a version that learnt the estimated
#: reward (before outcomes were learnt) means something else and is not loaded.
TARGET = "outcome-residual"

#: The location one-hot's columns: each location has its own baseline (see DecisionModel).
_LOCATION_COLUMNS = (FEATURES.index("at_robot"), FEATURES.index("at_cloud"))
#: The baseline is the mean of a location's outcomes, of the latest this many once there are more.
BASELINE_SPAN = 32

_ADAM_BETAS = (0.9, 0.999)
_ADAM_EPS = 1e-8

_torch: Any = None


def _load_torch() -> Any:
    """Import torch on first use and keep it to one thread."""
    global _torch
    if _torch is None:
        import torch

        # Tiny matmuls: more threads only add synchronisation (ARCHITECTURE.md, measured ceilings).
        torch.set_num_threads(1)
        _torch = torch
    return _torch


@dataclass(frozen=True, slots=True)
class Features:
    """Describe a component's situation as the model sees it; values are roughly unit-scaled.

    cpu/ram/bandwidth_available: free share (0-1) of the robot's CPU, memory and link;
    latency: round trip to the cloud in seconds; loss: message or packet loss rate (0-1);
    battery: charge (0-1, 1 on mains); location: the component's active location (one-hot);
    cost_robot/cost_cloud: the policy's cost of running the component at each location.
    """

    cpu_available: float = 1.0
    ram_available: float = 1.0
    bandwidth_available: float = 1.0
    latency: float = 0.0
    loss: float = 0.0
    battery: float = 1.0
    location: Side = "robot"
    cost_robot: float = 0.0
    cost_cloud: float = 0.0

    def as_dict(self) -> dict[str, float | str]:
        """Return the fields as plain data (dataclasses.asdict is ten times slower: 2000 of these a second)."""
        return {
            "cpu_available": self.cpu_available,
            "ram_available": self.ram_available,
            "bandwidth_available": self.bandwidth_available,
            "latency": self.latency,
            "loss": self.loss,
            "battery": self.battery,
            "location": self.location,
            "cost_robot": self.cost_robot,
            "cost_cloud": self.cost_cloud,
        }

    def vector(self, scale: float = 1.0) -> list[float]:
        """Return the model input, in the order of FEATURES, costs squashed (:func:`squash`) in units of ``scale``."""
        return [
            self.cpu_available,
            self.ram_available,
            self.bandwidth_available,
            self.latency,
            self.loss,
            self.battery,
            1.0 if self.location == "robot" else 0.0,
            1.0 if self.location == "cloud" else 0.0,
            squash(self.cost_robot, scale),
            squash(self.cost_cloud, scale),
        ]


def squash(value: float, scale: float) -> float:
    """Return a cost on the network's scale: linear within ``scale`` of zero, logarithmic beyond, sign kept.

    A component that burns ten times what it declares costs about ten times the estimate on the robot,
    in every condition: on this scale that is one constant offset, learnt from a few outcomes.
    """
    return math.copysign(math.log1p(abs(value) / scale), value)


def unsquash(value: float, scale: float) -> float:
    """Invert :func:`squash`."""
    return math.copysign(scale * math.expm1(min(abs(value), 700.0)), value)


class DecisionModel:
    """Predict how far the policy's estimate of a location's cost is off, with a small MLP trained online.

    Its input is the component's situation (:class:`Features`, ``location`` the location whose cost
    is predicted); its output, the measured cost there minus the estimate, both squashed (:func:`squash`).
    That output is a per-location baseline, the running mean of the outcomes there, plus what the MLP
    learns of the rest: a component that burns ten times what it declares is off by about the same
    amount everywhere, which the mean has from the first outcome, while the MLP's gradient steps would
    take tens of outcomes to reach it (the decision waits for the network to be trusted meanwhile).
    """

    def __init__(
        self,
        config: NeuralNetworkConfig | None = None,
        *,
        n_features: int = N_FEATURES,
        buffer_size: int = 256,
        batch_size: int = 32,
        optimizer: OptimizerName = "adam",
    ) -> None:
        torch = _load_torch()
        self.config = config or NeuralNetworkConfig()
        self.n_features = n_features
        self.buffer_size = buffer_size
        self.batch_size = batch_size
        self.optimizer = optimizer
        widths = [n_features, *self.config.hidden_layers, 1]
        self.params: list[Tensor] = []
        for fan_in, fan_out in pairwise(widths):
            # torch.nn.Linear's default initialisation, without the Module overhead.
            bound = 1.0 / math.sqrt(fan_in)
            self.params.append(torch.empty(fan_out, fan_in).uniform_(-bound, bound))
            self.params.append(torch.empty(fan_out).uniform_(-bound, bound))
        self.exp_avg = [torch.zeros_like(p) for p in self.params] if optimizer == "adam" else []
        self.exp_avg_sq = [torch.zeros_like(p) for p in self.params] if optimizer == "adam" else []
        self.steps = 0
        self.samples_seen = 0
        self.since_training = 0
        # A flat float32 ring of (features..., reward) rows: 4 bytes a value, no Python objects per sample.
        self._row = n_features + 1
        self.buffer = array("f", bytes(4 * self._row * buffer_size))
        self.buffered = 0
        self._next_row = 0
        # Per location (robot, cloud): the mean of its outcomes, and how many it holds (see BASELINE_SPAN).
        self.baseline = [0.0, 0.0]
        self.baseline_seen = [0, 0]

    def location_of(self, features: Sequence[float]) -> int | None:
        """Return the index of the location a feature vector is at (None: not a location one-hot)."""
        if self.n_features != N_FEATURES:
            return None
        robot, cloud = (features[c] for c in _LOCATION_COLUMNS)
        if robot == 1.0 and cloud == 0.0:
            return 0
        if robot == 0.0 and cloud == 1.0:
            return 1
        return None

    def offset(self, features: Sequence[float]) -> float:
        """Return the baseline a feature vector's prediction starts from."""
        where = self.location_of(features)
        return 0.0 if where is None else self.baseline[where]

    @property
    def signature(self) -> tuple[Any, ...]:
        """Return what models must share to be evaluated in one batch."""
        return (self.config.activation, self.optimizer, self.batch_size, tuple(p.shape for p in self.params))

    @property
    def trained(self) -> bool:
        """Tell whether the model has seen enough samples for its predictions to be trusted."""
        return self.samples_seen >= self.config.trained_after

    def predict(self, features: Sequence[float]) -> float:
        """Return the prediction for one feature vector (the estimate's error, in the decider's scale)."""
        return predict_many([self], [features])[0]

    def record(self, features: Sequence[float], reward: float) -> bool:
        """Store a sample and tell whether a training step is due (every warmup_train_every until trained)."""
        start = self._next_row * self._row
        self.buffer[start : start + self._row] = array("f", [*features, reward])
        where = self.location_of(features)
        if where is not None:
            self.baseline_seen[where] += 1
            weight = 1 / min(self.baseline_seen[where], BASELINE_SPAN)
            self.baseline[where] += weight * (reward - self.baseline[where])
        self._next_row = (self._next_row + 1) % self.buffer_size
        self.buffered = min(self.buffered + 1, self.buffer_size)
        # Training every warm-up sample would cost 2000 components a quarter of a core until trained.
        every = self.config.train_every if self.trained else self.config.warmup_train_every
        self.samples_seen += 1
        self.since_training += 1
        return self.since_training >= every

    def observe(self, features: Sequence[float], reward: float) -> float | None:
        """Store a sample and train if due; return the training loss, or None if no step ran."""
        if self.record(features, reward):
            return train_many([self])[0]
        return None

    def train_step(self) -> float:
        """Run one training step on a minibatch of the replay buffer and return its loss."""
        return train_many([self])[0]

    def size_bytes(self) -> int:
        """Return the bytes held by parameters, optimizer state and the replay buffer."""
        tensors = [*self.params, *self.exp_avg, *self.exp_avg_sq]
        return sum(t.numel() * t.element_size() for t in tensors) + self.buffer.itemsize * len(self.buffer)

    def state_dict(self) -> dict[str, Any]:
        """Return everything needed to resume this model after a Skill restart."""
        torch = _load_torch()
        return {
            "target": TARGET,
            "shape": [self.n_features, *self.config.hidden_layers, 1],
            "activation": self.config.activation,
            "optimizer": self.optimizer,
            "params": [p.clone() for p in self.params],
            "exp_avg": [t.clone() for t in self.exp_avg],
            "exp_avg_sq": [t.clone() for t in self.exp_avg_sq],
            "steps": self.steps,
            "samples_seen": self.samples_seen,
            "since_training": self.since_training,
            "buffer": torch.frombuffer(bytearray(self.buffer), dtype=torch.float32),
            "buffered": self.buffered,
            "next_row": self._next_row,
            "baseline": list(self.baseline),
            "baseline_seen": list(self.baseline_seen),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore a state saved by state_dict; raise ValueError if the shape or optimizer differs."""
        shape = [self.n_features, *self.config.hidden_layers, 1]
        if state.get("target") != TARGET:
            raise ValueError(f"saved network learnt {state.get('target', 'the estimated reward')!r}, not {TARGET!r}")
        if state["shape"] != shape or state["activation"] != self.config.activation:
            raise ValueError(f"saved network {state['shape']}/{state['activation']} does not match {shape}")
        if state["optimizer"] != self.optimizer or state["buffer"].numel() != len(self.buffer):
            raise ValueError("saved network was trained with another optimizer or buffer size")
        self.params = [p.clone() for p in state["params"]]
        self.exp_avg = [t.clone() for t in state["exp_avg"]]
        self.exp_avg_sq = [t.clone() for t in state["exp_avg_sq"]]
        self.steps = int(state["steps"])
        self.samples_seen = int(state["samples_seen"])
        self.since_training = int(state["since_training"])
        self.buffer = array("f", state["buffer"].tolist())
        self.buffered = int(state["buffered"])
        self._next_row = int(state["next_row"])
        # Saved before baselines: that network learnt the whole error, which a zero baseline leaves to it.
        self.baseline = [float(v) for v in state.get("baseline", [0.0, 0.0])]
        self.baseline_seen = [int(v) for v in state.get("baseline_seen", [0, 0])]

    def to_bytes(self) -> bytes:
        """Serialise the model (torch.save format, tensors only)."""
        torch = _load_torch()
        out = io.BytesIO()
        torch.save(self.state_dict(), out)
        return out.getvalue()

    @classmethod
    def from_bytes(cls, data: bytes, config: NeuralNetworkConfig | None = None, **kwargs: Any) -> DecisionModel:
        """Rebuild a model saved by to_bytes under the given configuration."""
        torch = _load_torch()
        model = cls(config, **kwargs)
        model.load_state_dict(torch.load(io.BytesIO(data), weights_only=True))
        return model

    def save(self, path: str | os.PathLike[str]) -> None:
        """Write the model to a file atomically, so a crash mid-write keeps the previous one."""
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_bytes(self.to_bytes())
        tmp.replace(path)

    @classmethod
    def load(
        cls, path: str | os.PathLike[str], config: NeuralNetworkConfig | None = None, **kwargs: Any
    ) -> DecisionModel:
        """Read a model written by save."""
        return cls.from_bytes(Path(path).read_bytes(), config, **kwargs)


def _activate(x: Any, activation: str) -> Any:
    """Apply the configured activation."""
    torch = _load_torch()
    if activation == "relu":
        return torch.relu(x)
    if activation == "tanh":
        return torch.tanh(x)
    return torch.sigmoid(x)


def _forward(params: Sequence[Any], x: Any, activation: str) -> Any:
    """Run stacked MLPs: params are [k, out, in] weights and [k, out] biases, x is [k, batch, in]."""
    torch = _load_torch()
    last = len(params) - 2
    for i in range(0, len(params), 2):
        x = torch.baddbmm(params[i + 1].unsqueeze(1), x, params[i].transpose(1, 2))
        if i < last:
            x = _activate(x, activation)
    return x


def _groups(models: Sequence[DecisionModel]) -> dict[tuple[Any, ...], list[int]]:
    """Group model indices by shape, so each group runs as one batch."""
    groups: dict[tuple[Any, ...], list[int]] = {}
    for i, model in enumerate(models):
        groups.setdefault(model.signature, []).append(i)
    return groups


def predict_many(models: Sequence[DecisionModel], features: Sequence[Sequence[float]]) -> list[float]:
    """Predict for many components at once, one forward pass per model shape."""
    torch = _load_torch()
    out = [math.nan] * len(models)
    with torch.no_grad():
        for indices, group in ((ix, [models[i] for i in ix]) for ix in _groups(models).values()):
            if len(group) == 1:
                params = [p.unsqueeze(0) for p in group[0].params]
            else:
                params = [torch.stack(ps) for ps in zip(*(m.params for m in group), strict=True)]
            x = torch.tensor([features[i] for i in indices], dtype=torch.float32).unsqueeze(1)
            y = _forward(params, x, group[0].config.activation).reshape(-1).tolist()
            for i, value in zip(indices, y, strict=True):
                out[i] = value + models[i].offset(features[i])
    return out


def _stack(tensors: Sequence[Any]) -> Any:
    """Stack tensors on a new first dimension; a single one is a view, so in-place updates reach it."""
    return tensors[0].unsqueeze(0) if len(tensors) == 1 else _load_torch().stack(tensors)


def train_many(models: Sequence[DecisionModel]) -> list[float]:
    """Run one training step (mean squared error) on each model, batched per shape; return the losses.

    Adam is applied elementwise with each model's own step count and learning rate, so a batched
    step equals a step of each model alone.
    """
    torch = _load_torch()
    losses = [math.nan] * len(models)
    for indices in _groups(models).values():
        group = [models[i] for i in indices]
        first = group[0]
        rows = []
        for model in group:
            ring = torch.frombuffer(model.buffer, dtype=torch.float32).view(model.buffer_size, model._row)
            rows.append(ring[torch.randint(max(model.buffered, 1), (model.batch_size,))])
        batch = _stack(rows)
        x, target = batch[..., :-1], batch[..., -1:]
        if first.n_features == N_FEATURES:
            # The MLP learns what the location's baseline leaves: rows at a location less its current mean.
            robot, cloud = (x[..., c : c + 1] for c in _LOCATION_COLUMNS)
            at_robot = ((robot == 1.0) & (cloud == 0.0)).float()
            at_cloud = ((robot == 0.0) & (cloud == 1.0)).float()
            baselines = torch.tensor([m.baseline for m in group], dtype=torch.float32).view(len(group), 1, 2)
            target = target - at_robot * baselines[..., :1] - at_cloud * baselines[..., 1:]
        params = [_stack(ps).requires_grad_() for ps in zip(*(m.params for m in group), strict=True)]
        per_model = ((_forward(params, x, first.config.activation) - target) ** 2).mean(dim=(1, 2))
        # The models are independent, so the gradient of the sum is each model's own gradient.
        grads = torch.autograd.grad(per_model.sum(), params)
        for model in group:
            model.steps += 1
            model.since_training = 0
        lr = torch.tensor([m.config.learning_rate for m in group])
        adam = first.optimizer == "adam"
        if adam:
            beta1, beta2 = _ADAM_BETAS
            steps = torch.tensor([float(m.steps) for m in group])
            step_size = lr / (1 - beta1**steps)
            bias2_sqrt = torch.sqrt(1 - beta2**steps)
        with torch.no_grad():
            for j, (param, grad) in enumerate(zip(params, grads, strict=True)):
                view = (-1,) + (1,) * (grad.dim() - 1)
                weights = param.detach()
                if adam:
                    m1 = _stack([m.exp_avg[j] for m in group]).lerp_(grad, 1 - beta1)
                    m2 = _stack([m.exp_avg_sq[j] for m in group]).mul_(beta2).addcmul_(grad, grad, value=1 - beta2)
                    denom = (m2.sqrt() / bias2_sqrt.view(view)).add_(_ADAM_EPS)
                    weights.sub_(step_size.view(view) * m1 / denom)
                else:
                    weights.sub_(lr.view(view) * grad)
                if len(group) > 1:  # a single model was updated in place through its views
                    for k, model in enumerate(group):
                        model.params[j].copy_(weights[k])
                        if adam:
                            model.exp_avg[j].copy_(m1[k])
                            model.exp_avg_sq[j].copy_(m2[k])
        for i, loss in zip(indices, per_model.tolist(), strict=True):
            losses[i] = loss
    return losses
