"""The hog scenario's short form: a component past its CPU and memory limits beside another, real agent and cloud."""

from __future__ import annotations

import os

import pytest

from benchmarks.chaos import hog
from bridgeos_agent.runtime.cgroups import Cgroups

pytestmark = [
    pytest.mark.skipif(
        Cgroups("probe").hierarchy is None, reason="needs writable cgroups (v2 cpu+memory, or v1): run as root"
    ),
    pytest.mark.timeout(180),
]


@pytest.fixture(autouse=True)
def chaos_database(monkeypatch: pytest.MonkeyPatch) -> None:
    """Give the scenario's cloud a database beside the test database, and the test's Redis."""
    monkeypatch.setenv("BRIDGEOS_CHAOS_DATABASE_URL", os.environ["DATABASE_URL"] + "_chaos")
    monkeypatch.setenv("BRIDGEOS_CHAOS_REDIS_URL", os.environ["REDIS_URL"])


def test_a_hog_is_held_to_its_limits_and_the_robot_keeps_working() -> None:
    (outcome,) = hog.run(quick=True)
    figures = outcome.figures
    assert outcome.passed, outcome.detail
    assert figures["hog_cpu_cores"] <= figures["hog_cpu_limit"] * 1.15
    assert figures["hog_oom_kills_reported"] >= 1 and figures["hog_restarts"] >= 1
    assert figures["ticker_rate_kept"] >= 0.6
