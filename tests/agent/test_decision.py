"""Test the per-component offloading decisions (thesis Algorithms 8 and 9) and their networks learning outcomes."""

from __future__ import annotations

import dataclasses
import math
import random
import statistics
import subprocess
import sys

import pytest

from bridgeos_agent.decision import (
    Decider,
    DecisionInput,
    DecisionModel,
    Features,
    Outcome,
    decide_and_learn,
    decide_batch,
    predict_many,
    train_due,
    train_many,
)
from bridgeos_agent.decisionmodel import squash, unsquash
from bridgeos_agent.skillconfig import ManagerConfig, NeuralNetworkConfig

torch = pytest.importorskip("torch")


def manager(trained_after: int = 20, threshold: float = 0.1, **network: object) -> ManagerConfig:
    """Return a manager config with a small network that trusts itself early."""
    return ManagerConfig(
        threshold=threshold,
        neural_network=NeuralNetworkConfig(trained_after=trained_after, **network),
    )


def at_robot(reward: float, **kwargs: object) -> DecisionInput:
    """Return the input of a movable component running on the robot."""
    kwargs.setdefault("features", Features(cost_robot=1.0))
    return DecisionInput(location="robot", estimated_reward=reward, **kwargs)


def test_agent_package_imports_without_loading_torch() -> None:
    code = "import sys, bridgeos_agent, bridgeos_agent.decision; assert 'torch' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_untrained_decider_follows_the_estimate() -> None:
    decider = Decider("detector", manager(threshold=0.1), hysteresis=0.0)
    high = decider.decide(at_robot(0.5), now=0.0)
    decider.last_move = None
    low = decider.decide(at_robot(0.05), now=1.0)
    assert high.migrate and high.target == "cloud" and high.prediction is None and not high.trained
    assert not low.migrate and low.target == "robot"
    assert "estimate" in high.reason and "estimate" in low.reason


def test_reward_exactly_at_threshold_migrates_and_just_below_stays() -> None:
    decider = Decider("detector", manager(threshold=0.2), hysteresis=0.0, cooldown=0.0)
    assert decider.decide(at_robot(0.2), now=0.0).migrate
    assert not decider.decide(at_robot(0.1999), now=1.0).migrate


def test_hysteresis_requires_a_margin_above_threshold() -> None:
    decider = Decider("detector", manager(threshold=0.1), hysteresis=0.05, cooldown=0.0)
    assert not decider.decide(at_robot(0.14), now=0.0).migrate
    assert decider.decide(at_robot(0.151), now=1.0).migrate


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


def test_manual_recommendation_wins_over_the_reward() -> None:
    decider = Decider("detector", manager(), cooldown=3600.0)
    decider.last_move = 0.0
    assert decider.decide(at_robot(-5.0, recommendation=True), now=1.0).migrate
    stay = decider.decide(at_robot(5.0, recommendation=False), now=2.0)
    assert not stay.migrate and stay.reason == "recommendation"


def test_manual_mode_moves_only_on_recommendation() -> None:
    decider = Decider("detector", manager())
    assert not decider.decide(at_robot(5.0, mode="manual"), now=0.0).migrate
    assert decider.decide(at_robot(0.0, mode="manual", recommendation=True), now=1.0).migrate


@pytest.mark.parametrize("location", ["robot", "cloud"])
def test_fixed_location_never_moves(location: str) -> None:
    decider = Decider("driver", manager(), cooldown=0.0)
    for second in range(50):
        decision = decider.decide(
            DecisionInput(location=location, estimated_reward=9.0, required_location=location, recommendation=True),
            now=float(second),
        )
        assert not decision.migrate and decision.reason == "fixed location"
    assert decider._model is None  # never built, never needed torch


@pytest.mark.parametrize(
    ("mode", "location", "moves"),
    [("robot", "cloud", True), ("robot", "robot", False), ("cloud", "robot", True), ("cloud", "cloud", False)],
)
def test_robot_and_cloud_modes_keep_components_on_their_side(mode: str, location: str, moves: bool) -> None:
    decider = Decider("detector", manager())
    decision = decider.decide(DecisionInput(location=location, estimated_reward=-9.0, mode=mode), now=0.0)
    assert decision.migrate is moves
    assert decision.target == mode


def test_no_move_to_the_robot_without_free_resources() -> None:
    decider = Decider("detector", manager())
    decision = decider.decide(
        DecisionInput(location="cloud", estimated_reward=9.0, resources_ok=False, recommendation=True), now=0.0
    )
    assert not decision.migrate and "resources" in decision.reason


def moves_in_an_hour(decider: Decider, seed: int) -> int:
    """Count migrations over an hour of 1 Hz decisions with a noisy reward around the threshold."""
    rng = random.Random(seed)
    location, moves = "robot", 0
    for second in range(3600):
        # The cloud is slightly better; the estimate is noisy and antisymmetric in location.
        benefit = 0.12 if location == "robot" else -0.12
        given = DecisionInput(location=location, estimated_reward=benefit + rng.gauss(0, 0.3))
        if decider.decide(given, now=float(second)).migrate:
            location = "cloud" if location == "robot" else "robot"
            moves += 1
    return moves


def test_hysteresis_and_cooldown_stop_flapping_under_noise() -> None:
    config = manager(trained_after=1_000_000)
    naive = moves_in_an_hour(Decider("detector", config, hysteresis=0.0, cooldown=0.0, noise_margin=0.0), seed=7)
    damped = moves_in_an_hour(Decider("detector", config, hysteresis=0.05, cooldown=120.0, noise_margin=0.0), seed=7)
    assert naive > 500
    assert damped <= 3600 / 120 + 1
    assert damped >= 1


def test_noise_margin_keeps_a_noisy_stable_reward_from_flapping_without_a_cooldown() -> None:
    config = manager(trained_after=1_000_000)
    for seed in (1, 2, 3):
        single = moves_in_an_hour(Decider("d", config, hysteresis=0.3, cooldown=0.0, noise_margin=0.0), seed=seed)
        damped = Decider("d", config, hysteresis=0.3, cooldown=0.0, noise_margin=3.0)
        assert moves_in_an_hour(damped, seed=seed) <= single / 10
        assert damped.reward_noise == pytest.approx(0.3, rel=0.5)


def test_a_reward_within_the_noise_moves_only_when_three_decisions_in_a_row_clear_the_hysteresis() -> None:
    decider = Decider("detector", manager(threshold=0.1, trained_after=1_000_000), hysteresis=0.05, cooldown=0.0)
    rng = random.Random(4)
    stays = [decider.decide(at_robot(-0.5 + rng.gauss(0, 0.2)), now=float(second)) for second in range(30)]
    assert not any(d.migrate for d in stays)
    assert stays[-1].margin is not None and stays[-1].margin > 3 * 0.1  # the noise's, not the hysteresis
    first, second = (decider.decide(at_robot(0.3), now=now) for now in (30.0, 31.0))
    assert not first.migrate and not second.migrate and "within the noise" in second.reason
    assert decider.decide(at_robot(0.3), now=32.0).migrate  # the third in a row
    cloud = [
        # The same costs' level as on the robot: the noise is measured as a share of it (Decider.level).
        decider.decide(DecisionInput(location="cloud", estimated_reward=r, features=Features(cost_robot=1.0)), 33.0 + i)
        for i, r in enumerate([0.3, 0.3, -0.5, 0.3, 0.3])
    ]
    assert not any(d.migrate for d in cloud)  # the run of confirmations was broken


def test_noise_margin_still_moves_at_once_on_a_real_change() -> None:
    decider = Decider("detector", manager(threshold=0.1, trained_after=1_000_000), hysteresis=0.05, cooldown=0.0)
    rng = random.Random(4)
    for second in range(30):
        decider.decide(at_robot(-0.5 + rng.gauss(0, 0.2)), now=float(second))
    jump = decider.decide(at_robot(5.0), now=30.0)  # the conditions changed: far above the noise
    assert jump.migrate and jump.target == "cloud"


def test_the_noise_of_a_busy_robot_s_large_costs_does_not_hold_back_a_change_at_an_idle_robot_s_small_ones() -> None:
    # Costs over a busy robot's little free CPU: about 200, swinging by 20 (a tenth of them).
    decider = Decider("detector", manager(threshold=2.0, trained_after=1_000_000), hysteresis=3.0, cooldown=0.0)
    rng = random.Random(5)
    rewards = []
    for second in range(20):
        cost_robot = 220 * (1 + rng.gauss(0, 0.1))
        busy = Features(cost_robot=cost_robot, cost_cloud=20.0, location="cloud")
        rewards.append(20 - cost_robot)
        decider.decide(DecisionInput(location="cloud", estimated_reward=rewards[-1], features=busy), now=second)
    # Measured in cost units, that noise (noise_margin 4 x about 20) would hold back any reward below 80.
    assert statistics.stdev(rewards) > 15
    # The robot idles: costs of 30 and 50, the cloud's 20 more. The noise is measured on the costs' relative
    # difference, which barely moved while the robot's cost dwarfed the cloud's: the change moves at once.
    idle = Features(cost_robot=30.0, cost_cloud=50.0, location="cloud")
    decision = decider.decide(DecisionInput(location="cloud", estimated_reward=20.0, features=idle), now=20.0)
    assert decision.margin is not None and decision.margin < 20.0
    assert decision.migrate and decision.target == "robot", decision.reason


def test_noise_measured_at_one_level_keeps_its_share_at_that_level() -> None:
    decider = Decider("detector", manager(threshold=2.0, trained_after=1_000_000), hysteresis=3.0, cooldown=0.0)
    rng = random.Random(6)
    features = Features(cost_robot=20.0, cost_cloud=20.0)
    for second in range(40):
        decider.decide(at_robot(rng.gauss(-1.0, 5.0), features=features), now=second)
    # The stable phase's noise (sd 5) is what the margin holds to, in cost units, at the same level.
    assert decider.reward_noise == pytest.approx(5.0, rel=0.5)
    # Busier: the same share of costs ten times larger is ten times the noise.
    decider.decide(at_robot(-1.0, features=Features(cost_robot=245.0, cost_cloud=245.0)), now=40.0)
    assert decider.reward_noise == pytest.approx(50.0, rel=0.5)


def test_noise_margin_is_the_hysteresis_until_the_noise_is_measured_or_when_quiet() -> None:
    decider = Decider("detector", manager(threshold=0.1), hysteresis=0.05, cooldown=0.0)
    assert decider.reward_noise is None and decider.margin == 0.05
    for second in range(10):
        decider.decide(at_robot(-0.2), now=float(second))
    assert decider.reward_noise == 0.0 and decider.margin == 0.05
    assert decider.decide(at_robot(0.151), now=10.0).migrate


def test_noise_is_measured_across_a_move_as_the_cloud_gain() -> None:
    decider = Decider("detector", manager(threshold=0.1), hysteresis=0.05, cooldown=0.0, noise_margin=3.0)
    for second in range(10):
        location = "robot" if second % 2 else "cloud"
        gain = 0.02 if second % 2 else -0.02  # the same cloud gain, seen from either side
        decider.decide(DecisionInput(location=location, estimated_reward=gain), now=float(second))
    assert decider.reward_noise == 0.0


@pytest.mark.parametrize("setting", ["hysteresis", "cooldown", "noise_margin"])
@pytest.mark.parametrize("value", [-1.0, float("nan"), float("inf")])
def test_bad_hysteresis_cooldown_or_noise_margin_is_refused(setting: str, value: float) -> None:
    with pytest.raises(ValueError, match=setting):
        Decider("detector", manager(), **{setting: value})
    with pytest.raises(ValueError, match=setting):
        ManagerConfig(**{setting: value})


def test_decision_record_is_plain_data_for_the_cloud() -> None:
    record = Decider("detector", manager()).decide(at_robot(0.5), now=12.5).as_dict()
    assert record["component"] == "detector" and record["at"] == 12.5
    assert record["features"]["cost_robot"] == 1.0 and record["features"]["location"] == "robot"
    assert {"estimated_reward", "prediction", "threshold", "hysteresis", "reason", "migrate", "target"} <= set(record)
    assert record["decided_by"] == "estimate" and record["network_error"] is None


def test_batch_decisions_match_single_decisions() -> None:
    torch.manual_seed(3)
    deciders = [Decider(f"c{i}", manager(trained_after=3, warmup_train_every=1), hysteresis=0.01) for i in range(40)]
    for d in deciders:
        for _ in range(3):
            d.model.observe(Features(cost_robot=random.random()).vector(d.scale), random.uniform(-1, 1))
    features = [Features(cost_robot=random.random(), cost_cloud=random.random()) for _ in deciders]
    inputs = [DecisionInput("robot", f.cost_robot - f.cost_cloud, features=f) for f in features]
    expected = []
    for d, f in zip(deciders, features, strict=True):
        # The network corrects the estimated cost at the target (the cloud); the reward follows.
        predicted = d.model.predict(dataclasses.replace(f, location="cloud").vector(d.scale))
        expected.append(f.cost_robot - d.corrected(f.cost_cloud, predicted))
    decisions = decide_batch(deciders, inputs, now=0.0)
    assert [d.component for d in decisions] == [d.component for d in deciders]
    assert [d.prediction for d in decisions] == pytest.approx(expected, abs=1e-5)
    # No held-out outcome scored yet: the estimate decides every one.
    assert not any(d.trusted for d in decisions) and {d.decided_by for d in decisions} == {"estimate"}
    assert [d.migrate for d in decisions] == [i.estimated_reward >= 0.11 for i in inputs]


def test_decide_and_learn_leaves_the_training_step_to_train_due() -> None:
    torch.manual_seed(1)
    decider = Decider("detector", delay_manager(trained_after=1))
    decisions, due = decide_and_learn([decider], [misdeclared("robot")], now=0.0)
    assert len(decisions) == 1 and due == [decider.model] and decider.model.steps == 0
    train_due(due)
    assert decider.model.steps == decider.config.neural_network.train_steps == 3


def test_hysteresis_and_cooldown_come_from_the_manager_config() -> None:
    config = ManagerConfig(threshold=0.1, hysteresis=0.2, cooldown=45.0)
    decider = Decider("detector", config)
    assert (decider.hysteresis, decider.cooldown) == (0.2, 45.0)
    assert not decider.decide(at_robot(0.29), now=0.0).migrate
    assert decider.decide(at_robot(0.31), now=1.0).migrate
    assert not decider.decide(at_robot(5.0), now=45.0).migrate  # cooling down
    assert decider.decide(at_robot(5.0), now=46.1).migrate
    assert ManagerConfig().cooldown == 30.0 and ManagerConfig().hysteresis == 0.05
    assert ManagerConfig().noise_margin == 4.0 and Decider("d", ManagerConfig(noise_margin=1.5)).noise_margin == 1.5


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
