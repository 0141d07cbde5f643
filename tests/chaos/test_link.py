"""The link scenario's short form: a robot's link cut and restored, against the real cloud and agent."""

from __future__ import annotations

import os

import pytest

from benchmarks.chaos import link

pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="cuts a link in a network namespace: needs root (ip netns)"),
    pytest.mark.timeout(180),
]


@pytest.fixture(autouse=True)
def chaos_database(monkeypatch: pytest.MonkeyPatch) -> None:
    """Give the scenario's cloud a database beside the test database, and the test's Redis."""
    monkeypatch.setenv("BRIDGEOS_CHAOS_DATABASE_URL", os.environ["DATABASE_URL"] + "_chaos")
    monkeypatch.setenv("BRIDGEOS_CHAOS_REDIS_URL", os.environ["REDIS_URL"])


def test_a_cut_link_is_taken_over_in_time_reverted_without_duplicates_and_its_backlog_delivered() -> None:
    (outcome,) = link.run(quick=True)
    figures = outcome.figures
    assert outcome.passed, outcome.detail
    assert figures["takeover_s"] <= figures["connection_lost_after_s"] + 2
    assert figures["duplicate_components"] == 0 and figures["missing_components"] == 0
    assert figures["backlog_points"] > 0 and figures["out_of_order"] == 0
    assert outcome.lost == 0 and outcome.duplicated == 0
    assert outcome.sent > 0 and outcome.stored == outcome.sent
