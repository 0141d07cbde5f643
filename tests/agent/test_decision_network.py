"""Test the decisions' networks: learning outcomes, when they are trusted, and how their models train and save."""

from __future__ import annotations

import dataclasses
import math
import random

import pytest

from bridgeos_agent.decision import (
    Decider,
    DecisionInput,
    DecisionModel,
    Features,
    Outcome,
    decide_and_learn,
    predict_many,
    train_due,
    train_many,
)
from bridgeos_agent.decisionmodel import squash, unsquash
from bridgeos_agent.skillconfig import ManagerConfig, NeuralNetworkConfig

torch = pytest.importorskip("torch")


def misdeclared(where: str, free: float = 1.3, declared_share: float = 0.1, cloud: float = 22.0) -> DecisionInput:
    """Return the input of a component that burns 0.2 cores but declares ``declared_share`` of that.

    Costed as offloading_quality's delay policy: on the robot 200 * cpu / free cores, in the cloud ``cloud``
    (22 over a good link). On the robot its cost is measured (the CPU it burns); from the cloud it is
    estimated from what it declares.
    """
    declared, burnt = 0.2 * declared_share, 0.2
    estimated_robot, realized_robot = 200 * declared / free, 200 * burnt / free
    if where == "robot":
        features = Features(cpu_available=free / 2, location="robot", cost_robot=realized_robot, cost_cloud=cloud)
        seen = Features(cpu_available=free / 2, location="robot", cost_robot=estimated_robot, cost_cloud=cloud)
        outcome = Outcome("robot", realized_robot, estimated_robot, seen)
        return DecisionInput("robot", realized_robot - cloud, features=features, outcome=outcome)
    features = Features(cpu_available=free / 2, location="cloud", cost_robot=estimated_robot, cost_cloud=cloud)
    return DecisionInput(
        "cloud", cloud - estimated_robot, features=features, outcome=Outcome("cloud", cloud, cloud, features)
    )


def delay_manager(trained_after: int = 5) -> ManagerConfig:
    """Return offloading_quality's decision settings, with a network allowed to decide after a few outcomes."""
    network = NeuralNetworkConfig(trained_after=trained_after, warmup_train_every=1, train_every=1, train_steps=3)
    return ManagerConfig(threshold=2.0, hysteresis=3.0, cooldown=0.0, neural_network=network)


def visited_robot(decider: Decider, decisions: int, declared_share: float = 0.1) -> None:
    """Feed a decider the outcomes of a stay on the robot (the decisions themselves are not acted on)."""
    rng = random.Random(2)
    for n in range(decisions):
        decider.decide(misdeclared("robot", free=1.3 + rng.uniform(-0.1, 0.1), declared_share=declared_share), n)


def test_network_learns_a_misdeclared_component_and_decides_once_it_beats_the_estimate() -> None:
    torch.manual_seed(1)
    decider = Decider("detector", delay_manager())
    visited_robot(decider, 20)
    network, estimate = decider.errors("robot")
    assert decider.trust("robot") and network is not None and estimate is not None and network <= 0.75 * estimate
    # Back in the cloud the estimate says the robot costs 3 against 22 here: it would move. The network,
    # having measured ~31 on the robot, keeps it in the cloud.
    decision = decider.decide(misdeclared("cloud"), now=100.0)
    assert decision.estimated_reward > 2.0 + 3.0
    assert decision.decided_by == "network" and decision.trusted and not decision.migrate
    assert decision.prediction is not None and decision.prediction < 0
    assert "network beats the estimate at the robot" in decision.reason
    assert decision.network_error == network and decision.estimate_error == estimate


def test_a_tenfold_misdeclaration_is_learnt_from_a_short_stay_on_the_robot() -> None:
    # offloading_quality's settings (trained after 3 outcomes): its 8 s phases leave a stay of a few decisions.
    for seed in (1, 2, 3):
        torch.manual_seed(seed)
        decider = Decider("detector", delay_manager(trained_after=3))
        visited_robot(decider, 7)
        network, estimate = decider.errors("robot")
        # Held out, the network is within a tenth of the estimate's error (the MLP alone: about half of it).
        assert decider.trust("robot") and network is not None and estimate is not None and network <= 0.1 * estimate
        decision = decider.decide(misdeclared("cloud"), now=100.0)
        assert decision.decided_by == "network" and not decision.migrate, decision.reason
        # The robot really costs about 31 against the cloud's 22 (the estimate says 3).
        assert decision.prediction is not None and -13 < decision.prediction < -5


def test_each_location_s_baseline_is_the_mean_of_its_outcomes_and_is_saved_with_the_network() -> None:
    model = DecisionModel(NeuralNetworkConfig())
    robot = Features(location="robot").vector()
    cloud = Features(location="cloud").vector()
    for target in (1.0, 2.0, 3.0):
        model.record(robot, target)
    model.record(cloud, 0.0)
    model.record([0.5] * len(robot), 9.0)  # not at a location (a one-hot of neither): no baseline's
    assert model.baseline == [pytest.approx(2.0), 0.0] and model.baseline_seen == [3, 1]
    # A prediction is the location's baseline plus the MLP's own output (the same for both here).
    mlp_only = Features(location="robot").vector()
    mlp_only[6] = 0.999  # not exactly at a location: the MLP alone
    assert model.predict(robot) - model.predict(mlp_only) == pytest.approx(2.0, abs=0.05)
    again = DecisionModel.from_bytes(model.to_bytes(), NeuralNetworkConfig())
    assert again.baseline == model.baseline and again.predict(robot) == pytest.approx(model.predict(robot))
    # The mean of the latest BASELINE_SPAN outcomes once there are more: a location's error can change.
    for _ in range(200):
        model.record(robot, -1.0)
    assert model.baseline[0] == pytest.approx(-1.0, abs=0.01)


def test_estimate_only_moves_the_misdeclared_component_back_to_the_robot() -> None:
    decider = Decider("detector", delay_manager(trained_after=1_000_000))
    visited_robot(decider, 20)
    decision = decider.decide(misdeclared("cloud"), now=100.0)
    assert decision.decided_by == "estimate" and not decision.trusted and decision.migrate
    assert decision.target == "robot"


def test_the_network_does_not_decide_where_the_estimate_is_right() -> None:
    torch.manual_seed(1)
    decider = Decider("detector", delay_manager())
    visited_robot(decider, 20, declared_share=1.0)  # declares what it burns: the estimate is exact
    assert decider.errors("robot")[1] == pytest.approx(0.0) and not decider.trust("robot")
    decision = decider.decide(misdeclared("cloud", declared_share=1.0), now=100.0)
    assert decision.decided_by == "estimate" and decision.prediction is not None
    assert "network not trusted at the robot" in decision.reason


def test_trust_needs_training_and_three_held_out_outcomes() -> None:
    torch.manual_seed(1)
    decider = Decider("detector", delay_manager(trained_after=50))
    visited_robot(decider, 20)
    assert not decider.trust("robot")  # fewer samples than trained_after
    fresh = Decider("detector", delay_manager(trained_after=1))
    visited_robot(fresh, 3)
    # The first outcome is seen by no network (it had never trained), so two are scored: not enough.
    assert len(fresh._scores["robot"]) == 2 and not fresh.trust("robot")
    assert fresh.errors("cloud") == (None, None) and not fresh.trust("cloud")


def test_cloud_outcomes_teach_the_network_nothing_to_correct() -> None:
    torch.manual_seed(1)
    decider = Decider("detector", delay_manager())
    for n in range(10):
        decider.decide(misdeclared("cloud"), now=float(n))
        decider.last_move = None
    assert decider.errors("cloud")[1] == 0.0 and not decider.trust("cloud")
    assert decider.model.samples_seen == 10
    # A network exactly as right as the estimate there (both never wrong) does not beat it either: found in a
    # full offloading_quality run, where a trusted cloud network moved a component on a noisy 5.2 against 5.
    outcome = misdeclared("cloud").outcome
    for _ in range(6):
        decider._learn(outcome, held_out=0.0)  # the network's held-out prediction: exactly right
    assert decider.errors("cloud") == (0.0, 0.0) and decider.model.trained and not decider.trust("cloud")


def test_outcome_error_and_the_networks_scale() -> None:
    outcome = Outcome("robot", realized=31.0, estimated=3.1, features=Features())
    assert outcome.error == pytest.approx(27.9)
    for value in (-250.0, -1.0, 0.0, 0.02, 3.1, 31.0, 1e6):
        assert unsquash(squash(value, 5.0), 5.0) == pytest.approx(value, rel=1e-9, abs=1e-12)
    # Linear near zero, logarithmic far away: a tenfold cost is about one offset wherever it is.
    assert squash(0.05, 5.0) == pytest.approx(0.01, rel=0.01)
    big = [squash(10 * c, 5.0) - squash(c, 5.0) for c in (100.0, 1000.0)]
    assert big[0] == pytest.approx(big[1], abs=0.1)
    assert Features(cost_robot=5.0).vector(5.0)[-2] == pytest.approx(math.log(2))


def test_a_network_saved_before_outcomes_were_learnt_is_refused() -> None:
    model = DecisionModel(NeuralNetworkConfig())
    state = model.state_dict()
    del state["target"]
    with pytest.raises(ValueError, match="estimated reward"):
        DecisionModel(NeuralNetworkConfig()).load_state_dict(state)


def test_default_network_is_trained_after_1000_samples() -> None:
    model = DecisionModel(NeuralNetworkConfig())
    sample = Features(cost_robot=0.3).vector()
    for _ in range(999):
        model.observe(sample, 0.3)
    assert not model.trained
    model.observe(sample, 0.3)
    # While warming up every sample is kept but only every fourth trains (warmup_train_every).
    assert model.trained and model.steps == 250


def test_warm_up_records_every_sample_and_trains_every_kth() -> None:
    model = DecisionModel(NeuralNetworkConfig(trained_after=100, warmup_train_every=3))
    sample = Features().vector()
    assert [model.observe(sample, 0.1) is not None for _ in range(9)] == [False, False, True] * 3
    assert model.samples_seen == 9 and model.buffered == 9 and model.steps == 3


def test_trained_network_retrains_every_train_every_samples() -> None:
    model = DecisionModel(NeuralNetworkConfig(trained_after=5, train_every=4, warmup_train_every=1))
    sample = Features().vector()
    for _ in range(5):
        model.observe(sample, 0.0)
    assert model.steps == 5
    assert [model.observe(sample, 0.0) is not None for _ in range(8)] == [False, False, False, True] * 2
    assert model.steps == 7


def test_unusable_prediction_falls_back_to_the_estimate() -> None:
    torch.manual_seed(1)
    decider = Decider("detector", delay_manager())
    visited_robot(decider, 20)
    for param in decider.model.params:
        param.fill_(float("nan"))
    decision = decider.decide(misdeclared("cloud"), now=100.0)
    assert decision.prediction is None and decision.decided_by == "estimate"
    # The estimate decides alone, held back by its own held-out error on the robot (see the next test).
    assert not decision.migrate and "within its held-out error there" in decision.reason
    exact = Decider("detector", delay_manager())
    visited_robot(exact, 20, declared_share=1.0)
    for param in exact.model.params:
        param.fill_(float("nan"))
    decision = exact.decide(misdeclared("robot", free=0.5, declared_share=1.0), now=100.0)
    assert decision.prediction is None and decision.decided_by == "estimate" and decision.migrate


def test_an_estimate_shown_wrong_at_the_target_moves_a_component_there_only_for_more_than_its_error() -> None:
    torch.manual_seed(1)
    decider = Decider("detector", delay_manager(trained_after=1))
    visited_robot(decider, 3)  # two held-out outcomes on the robot: the network may not decide yet
    _, estimate = decider.errors("robot")
    assert not decider.trust("robot") and estimate is not None and estimate > 1.0
    # In the cloud (22) the estimate says the robot costs 3 (it really costs ~31): a gain of 19 it has been
    # shown to be wrong by more than.
    decision = decider.decide(misdeclared("cloud"), now=100.0)
    assert decision.decided_by == "estimate" and decision.estimated_reward > 2.0 + 3.0 and not decision.migrate
    assert "within its held-out error there" in decision.reason and "estimate's doubt at the robot" in decision.reason
    # Over a poor link the cloud costs 70: the robot wins even at ten times the estimate.
    assert decider.decide(misdeclared("cloud", cloud=70.0), now=101.0).migrate
    # An estimate shown wrong the other way (the component burnt less than it declares, say starved on a busy
    # machine) is no reason to stay away: it still moves the component for a gain past the threshold.
    generous = Decider("detector", delay_manager(trained_after=1))
    visited_robot(generous, 3, declared_share=4.0)
    assert generous.errors("robot")[1] > 1.0 and generous.underestimate("robot") == 0.0
    # The robot estimated at 84 from the 0.8 declared, against a cloud at 150.
    back = generous.decide(misdeclared("cloud", free=1.9, declared_share=4.0, cloud=150.0), now=100.0)
    assert back.decided_by == "estimate" and back.migrate and "held-out error there" not in back.reason


def test_the_estimate_s_shortfall_counts_every_outcome_even_those_no_network_has_scored() -> None:
    torch.manual_seed(1)
    decider = Decider("detector", delay_manager(trained_after=1))
    visited_robot(decider, 1)  # a first stay cut short: one outcome, before any network could be asked
    assert decider.errors("robot") == (None, None) and decider.underestimate("robot") > 1.0
    held = decider.decide(misdeclared("cloud"), now=100.0)
    assert not held.migrate and "within its held-out error there" in held.reason
    # An estimate-only decider (its network never trains) keeps the thesis's estimate, without doubt.
    thesis = Decider("detector", delay_manager(trained_after=1_000_000))
    visited_robot(thesis, 1)
    assert thesis.decide(misdeclared("cloud"), now=100.0).migrate


def test_a_doubt_that_matters_must_be_cleared_by_the_reward_s_noise_too_however_confirmed() -> None:
    torch.manual_seed(1)
    decider = Decider("detector", delay_manager(trained_after=1))
    visited_robot(decider, 2)
    estimated = misdeclared("cloud").features.cost_robot
    doubt = decider.doubt(estimated, decider.underestimate("robot"))
    assert doubt > decider.hysteresis and decider.margin == decider.hysteresis  # no noise measured yet
    # A gain past the doubt by less than the margin: no run of decisions moves it.
    close = misdeclared("cloud", cloud=estimated + 2.0 + doubt + decider.hysteresis / 2)
    decisions = [decider.decide(close, now=100.0 + n) for n in range(5)]
    assert not any(d.migrate for d in decisions) and "within its held-out error there" in decisions[-1].reason
    assert decider.decide(misdeclared("cloud", cloud=estimated + 2.0 + doubt + 2 * decider.hysteresis), 106.0).migrate


def test_a_move_its_own_outcome_refutes_is_undone_within_the_cooldown() -> None:
    decider = Decider("detector", delay_manager(trained_after=1_000_000), cooldown=60.0)
    # The estimate says the robot costs 3 against the cloud's 22: it moves the component there.
    assert decider.decide(misdeclared("cloud"), now=0.0).migrate
    # There it costs 31, past the noise more than the 3 the move expected: back at once, cooldown or not.
    back = decider.decide(misdeclared("robot"), now=1.0)
    assert back.migrate and back.target == "cloud" and "refuting" in back.reason
    # A move its outcome bears out waits for the cooldown even when the conditions then turn.
    truthful = Decider("detector", delay_manager(trained_after=1_000_000), cooldown=60.0)
    assert truthful.decide(misdeclared("cloud", cloud=70.0, declared_share=1.0), now=0.0).migrate
    stay = truthful.decide(misdeclared("robot", declared_share=1.0), now=1.0)
    assert stay.estimated_reward > 2.0 + 3.0 and not stay.migrate and "cooling down" in stay.reason
    assert truthful.decide(misdeclared("robot", declared_share=1.0), now=61.0).migrate
    # A rule's move (a recommendation) expected nothing: after it, the cooldown holds as before.
    ruled = Decider("detector", delay_manager(trained_after=1_000_000), cooldown=60.0)
    assert ruled.decide(misdeclared("cloud"), now=0.0).migrate
    assert ruled.decide(dataclasses.replace(misdeclared("robot"), recommendation=True), now=1.0).migrate
    assert ruled.decide(dataclasses.replace(misdeclared("cloud"), recommendation=True), now=2.0).migrate
    assert "cooling down" in ruled.decide(misdeclared("robot"), now=3.0).reason


def test_decide_and_learn_leaves_the_training_step_to_train_due() -> None:
    torch.manual_seed(1)
    decider = Decider("detector", delay_manager(trained_after=1))
    decisions, due = decide_and_learn([decider], [misdeclared("robot")], now=0.0)
    assert len(decisions) == 1 and due == [decider.model] and decider.model.steps == 0
    train_due(due)
    assert decider.model.steps == decider.config.neural_network.train_steps == 3


def test_batched_training_step_equals_a_single_step() -> None:
    config = NeuralNetworkConfig(trained_after=100)
    alone, batched, other = (DecisionModel(config) for _ in range(3))
    for model in (alone, other):
        for _ in range(10):
            model.record([random.random() for _ in range(10)], random.random())
    batched.load_state_dict(alone.state_dict())
    torch.manual_seed(0)
    train_many([alone])
    torch.manual_seed(0)
    train_many([batched, other])
    probe = [[random.random() for _ in range(10)] for _ in range(5)]
    assert predict_many([alone] * 5, probe) == pytest.approx(predict_many([batched] * 5, probe), abs=1e-5)


def test_reloaded_model_predicts_identically(tmp_path) -> None:
    config = NeuralNetworkConfig(trained_after=10, hidden_layers=[8, 4], activation="tanh")
    model = DecisionModel(config)
    for _ in range(25):
        model.observe([random.random() for _ in range(10)], random.random())
    model.save(tmp_path / "detector.pt")
    again = DecisionModel.load(tmp_path / "detector.pt", config)
    probe = [[random.random() for _ in range(10)] for _ in range(20)]
    assert predict_many([again] * 20, probe) == predict_many([model] * 20, probe)
    assert again.samples_seen == 25 and again.trained and again.steps == model.steps
    assert again.buffer == model.buffer
    # Training resumes from the same optimizer state.
    torch.manual_seed(5)
    model.train_step()
    torch.manual_seed(5)
    again.train_step()
    assert predict_many([again] * 20, probe) == predict_many([model] * 20, probe)


def test_model_saved_under_another_shape_is_refused() -> None:
    data = DecisionModel(NeuralNetworkConfig(hidden_layers=[8])).to_bytes()
    with pytest.raises(ValueError, match="does not match"):
        DecisionModel.from_bytes(data, NeuralNetworkConfig(hidden_layers=[16, 16]))


@pytest.mark.parametrize("optimizer", ["adam", "sgd"])
def test_default_model_fits_in_50_kb(optimizer: str) -> None:
    model = DecisionModel(NeuralNetworkConfig(), optimizer=optimizer)
    assert model.size_bytes() <= 50_000
    assert len(model.to_bytes()) <= 50_000


def test_features_as_plain_data_cover_every_field() -> None:
    import dataclasses

    features = Features(cpu_available=0.5, loss=0.1, location="cloud", cost_robot=2.0, cost_cloud=1.0)
    assert features.as_dict() == dataclasses.asdict(features)
