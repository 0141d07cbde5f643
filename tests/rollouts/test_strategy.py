"""A rollout's batches, its abort rule and its gate conditions, as pure rules."""

from __future__ import annotations

import pytest
from django.core.exceptions import ValidationError

from rollouts.gates import Condition, parse_condition, parse_conditions
from rollouts.strategy import Share, Strategy, parse_strategy, share


def field_of(error: ValidationError) -> str:
    """The one field a ValidationError names."""
    (field,) = error.message_dict
    return field


@pytest.mark.parametrize(
    ("strategy", "total", "batches"),
    [
        ({"first": 1, "growth": "exponential", "factor": 2}, 20, [1, 2, 4, 8, 5]),
        ({"first": 1, "growth": "fixed"}, 5, [1, 1, 1, 1, 1]),
        ({"first": 2, "growth": "fixed"}, 5, [2, 2, 1]),
        ({"first": "10%", "growth": "exponential", "factor": 2}, 1000, [100, 200, 400, 300]),
        ({"first": "10%", "growth": "fixed"}, 30, [3] * 10),
        ({"first": "1%"}, 20, [1, 2, 4, 8, 5]),  # a share never rounds to no robot at all
        ({"first": "100%"}, 7, [7]),
        ({"first": 50}, 3, [3]),
        ({"first": 1, "factor": 1.5}, 10, [1, 2, 3, 4]),  # growth is at least one robot a batch
        ({}, 0, []),
    ],
)
def test_batches_start_with_the_canary_grow_and_cover_the_fleet_once(strategy, total, batches):
    sizes = parse_strategy(strategy).batches(total)
    assert sizes == batches
    assert sum(sizes) == total


def test_max_unavailable_holds_a_batch_to_some_robots_at_once():
    strategy = parse_strategy({"max_unavailable": "10%"})
    assert [strategy.at_once(n) for n in (1, 9, 10, 100, 1000)] == [1, 1, 1, 10, 100]
    assert parse_strategy({"max_unavailable": 3}).at_once(100) == 3
    assert Strategy().at_once(40) == 40


@pytest.mark.parametrize(
    ("threshold", "min_robots", "finished", "failed", "stops"),
    [
        (0, 1, 1, 1, True),  # the default: one failed robot stops the rollout
        (0, 1, 10, 0, False),
        (5, 20, 10, 1, False),  # too few robots finished to judge
        (5, 20, 20, 1, False),  # 5 % is not past 5 %
        (5, 20, 20, 2, True),
        (5, 20, 100, 5, False),
        (5, 20, 100, 6, True),
    ],
)
def test_the_abort_rule_judges_the_failed_share_once_enough_robots_finished(
    threshold, min_robots, finished, failed, stops
):
    strategy = parse_strategy({"failure_threshold_pct": threshold, "min_robots": min_robots})
    assert strategy.should_stop(finished, failed) is stops


def test_a_strategy_s_defaults_and_a_pause_until_resumed():
    assert parse_strategy(None) == Strategy()
    assert parse_strategy({}).first == Share(1, False)
    assert parse_strategy({"pause_s": None}).pause_s is None
    assert parse_strategy({"pause_s": 30, "soak_s": 2, "on_failure": "pause"}).on_failure == "pause"


@pytest.mark.parametrize(
    ("strategy", "field"),
    [
        ([], "strategy"),
        ({"first": 0}, "strategy.first"),
        ({"first": "0%"}, "strategy.first"),
        ({"first": "150%"}, "strategy.first"),
        ({"first": 1.5}, "strategy.first"),
        ({"first": "ten"}, "strategy.first"),
        ({"first": True}, "strategy.first"),
        ({"growth": "linear"}, "strategy.growth"),
        ({"factor": 1}, "strategy.factor"),
        ({"factor": "2"}, "strategy.factor"),
        ({"factor": float("nan")}, "strategy.factor"),
        ({"pause_s": -1}, "strategy.pause_s"),
        ({"max_unavailable": "-5%"}, "strategy.max_unavailable"),
        ({"soak_s": 10**9}, "strategy.soak_s"),
        ({"failure_threshold_pct": 101}, "strategy.failure_threshold_pct"),
        ({"min_robots": 2.5}, "strategy.min_robots"),
        ({"on_failure": "ignore"}, "strategy.on_failure"),
        ({"canary": 1}, "strategy.canary"),
    ],
)
def test_a_bad_strategy_names_its_field(strategy, field):
    with pytest.raises(ValidationError) as refused:
        parse_strategy(strategy)
    assert field_of(refused.value) == field


def test_a_share_reads_counts_and_percentages():
    assert share(3, "f") == Share(3, False)
    assert share("3", "f") == Share(3, False)
    assert share("12.5%", "f") == Share(12.5, True)
    assert str(share("12.5%", "f")) == "12.5%" and str(share(4, "f")) == "4"


@pytest.mark.parametrize(
    ("text", "condition"),
    [
        ("cpu < 0.8", Condition("cpu", "<", 0.8)),
        ("ram<=512", Condition("ram", "<=", 512.0)),
        ("metric:detections_per_s > 5", Condition("detections_per_s", ">", 5.0)),
        ("  metric:router.loss_rate == 0 ", Condition("router.loss_rate", "==", 0.0)),
        ("battery >= 1e-1", Condition("battery", ">=", 0.1)),
        ("metric:x != -3", Condition("x", "!=", -3.0)),
    ],
)
def test_a_condition_reads_a_metric_a_comparison_and_a_bound(text, condition):
    assert parse_condition(text) == condition


def test_a_condition_holds_on_the_window_s_mean_and_fails_without_points():
    gate = parse_condition("metric:detections_per_s > 5")
    assert gate.holds([4.0, 8.0]) is True
    assert gate.holds([4.0, 5.0, 6.0]) is False  # the mean, 5, is not above 5
    assert gate.holds([]) is False
    assert gate.holds([float("nan")]) is False
    assert str(gate) == "metric:detections_per_s > 5" and str(parse_condition("cpu<0.8")) == "cpu < 0.8"


@pytest.mark.parametrize(
    ("items", "field"),
    [
        ("cpu < 0.8", "gates.conditions"),
        (["cpu < 0.8", "gpu < 1"], "gates.conditions[1]"),
        (["cpu <"], "gates.conditions[0]"),
        (["cpu < 0.8; drop table"], "gates.conditions[0]"),
        (["metric: < 1"], "gates.conditions[0]"),
        ([5], "gates.conditions[0]"),
        (["cpu < inf"], "gates.conditions[0]"),
        (["cpu < 1e999"], "gates.conditions[0]"),
        (["cpu < 1"] * 33, "gates.conditions"),
    ],
)
def test_a_bad_condition_names_its_place(items, field):
    with pytest.raises(ValidationError) as refused:
        parse_conditions(items)
    assert field_of(refused.value) == field
    assert parse_conditions(None) == []
