"""The diskfull scenario's short form: the agent's disk full (and the cloud gone meanwhile), real agent and cloud."""

from __future__ import annotations

import os

import pytest

from benchmarks.chaos import diskfull

pytestmark = [
    pytest.mark.skipif(os.geteuid() != 0, reason="mounts a small tmpfs as the agent's disk: needs root"),
    pytest.mark.timeout(180),
]


@pytest.fixture(autouse=True)
def chaos_database(monkeypatch: pytest.MonkeyPatch) -> None:
    """Give the scenario's cloud a database beside the test database, and the test's Redis."""
    monkeypatch.setenv("BRIDGEOS_CHAOS_DATABASE_URL", os.environ["DATABASE_URL"] + "_chaos")
    monkeypatch.setenv("BRIDGEOS_CHAOS_REDIS_URL", os.environ["REDIS_URL"])


def test_a_full_disk_loses_no_state_event_and_no_metric_point_within_the_memory_budget() -> None:
    (outcome,) = diskfull.run(quick=True)
    figures = outcome.figures
    assert outcome.passed, outcome.detail
    assert figures["metric_points_kept_in_memory"] > 0, "the disk really was full under the outbox"
    # Within the memory budget nothing is lost; and every lost point is one the agent counted.
    assert outcome.lost == 0 and figures["metric_points_unstored"] == 0
    assert outcome.lost == figures["metric_points_dropped"], "every lost point is one the agent counted"
    assert outcome.duplicated == 0
    assert figures["state_events_crashes_seen"] > 0
    assert figures["state_events_lost"] == 0 and figures["state_events_out_of_order"] == 0
    assert figures["state_events_crashes_stored"] >= figures["state_events_crashes_seen"]
