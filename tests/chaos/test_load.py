"""Scenario 8 in its short form: robots stream while an operator's commands round-trip; nothing lost or doubled."""

from __future__ import annotations

import importlib

import pytest

from benchmarks.chaos import summary

pytestmark = pytest.mark.django_db(transaction=True)

load = importlib.import_module("benchmarks.chaos.load")


@pytest.mark.timeout(240)
def test_load_loses_and_duplicates_nothing_and_every_command_round_trips():
    outcomes = load.run(quick=True)

    failed = [f"{o.injected}: {o.detail}" for o in outcomes if not o.passed]
    assert not failed, failed
    (outcome,) = outcomes
    robots, seconds, _ = load.QUICK
    # 10 points/s per robot for the whole stream (a late last frame may miss the end), every one stored once.
    assert outcome.sent >= 0.9 * robots * 10 * seconds
    assert outcome.stored == outcome.sent
    assert summary(outcomes)["lost"] == 0
    assert summary(outcomes)["duplicated"] == 0
    assert outcome.figures["commands"] > 0
    assert outcome.figures["commands_failed"] == 0
    assert outcome.figures["command_p99_ms"] is not None
    assert outcome.figures["ingest_p95_ms"] is not None
