"""The agentkill scenario's short form: an agent killed -9 re-adopts its component and delivers its backlog once, in order."""

from __future__ import annotations

from benchmarks.chaos import agentkill


def test_a_killed_agent_readopts_its_component_and_delivers_its_backlog_once_in_order():
    (outcome,) = agentkill.run(quick=True)

    assert outcome.passed, outcome.row()
    assert outcome.sent > 0 and outcome.stored == outcome.sent
    assert outcome.lost == 0 and outcome.duplicated == 0
    assert "re-adopted, started 1 time(s), still running" in outcome.detail
    assert "in order" in outcome.detail
    assert outcome.recover_s is not None and outcome.recover_s <= 30
