"""The stores scenario's short form: Redis and PostgreSQL restarted under streaming robots lose nothing."""

from __future__ import annotations

from benchmarks.chaos import stores


def test_restarted_stores_lose_and_duplicate_no_point_and_recover():
    outcomes = stores.run(quick=True)

    assert len(outcomes) == 2
    assert all(outcome.passed for outcome in outcomes), [o.row() for o in outcomes]
    for outcome in outcomes:
        assert outcome.sent > 0 and outcome.stored == outcome.sent
        assert outcome.lost == 0 and outcome.duplicated == 0
        assert outcome.recover_s is not None and outcome.recover_s <= stores.RECOVER_GOAL_S
