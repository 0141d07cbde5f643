"""The processes scenario's short form: daphne, the Celery worker and beat killed with -9 lose nothing."""

from __future__ import annotations

from benchmarks.chaos import processes


def test_killed_cloud_processes_lose_and_duplicate_nothing_and_recover():
    outcomes = processes.run(quick=True)

    assert len(outcomes) == 3
    assert all(outcome.passed for outcome in outcomes), [o.row() for o in outcomes]
    daphne, worker, beat = outcomes
    assert daphne.sent > 0 and daphne.stored == daphne.sent
    assert daphne.lost == 0 and daphne.duplicated == 0
    assert daphne.figures["reconnect_s"] is not None and daphne.figures["reconnect_s"] <= processes.RECONNECT_GOAL_S
    # The killed task was redone by the next worker, within its visibility timeout and a worker start.
    assert worker.recover_s is not None and worker.recover_s <= 30
    assert beat.recover_s is not None and beat.recover_s <= 15
