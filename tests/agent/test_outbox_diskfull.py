"""The outbox on a full disk: frames kept in memory in order, metrics within a budget, never a crash."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest

from bridgeos_agent import protocol
from bridgeos_agent.outbox import Outbox
from bridgeos_agent.protocol import Event


def status(n: int) -> protocol.Envelope:
    return protocol.make(
        Event.COMPONENT_STATUS, {"skill": "s", "component": f"c{n}", "status": "running"}, now=1000.0 + n
    )


def metrics(points: int) -> protocol.Envelope:
    data = {"metrics": [{"name": "cpu", "value": float(i), "ts": 1000.0 + i} for i in range(points)]}
    return protocol.make(Event.METRICS, data, now=1000.0)


def fill(outbox: Outbox) -> list[protocol.Envelope]:
    """Make the file unable to grow (SQLITE_FULL, as on a full disk), then store events until one does not fit."""
    pages = outbox._db.execute("PRAGMA page_count").fetchone()[0]
    outbox._db.execute(f"PRAGMA max_page_count = {pages}")
    stored = []
    for n in range(10, 10_000):
        event = status(n)
        outbox.put(event)
        stored.append(event)
        if outbox.disk_full:
            return stored
    raise AssertionError("the outbox never filled")


def test_state_events_and_metric_frames_on_a_full_disk_are_kept_in_memory_in_order(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    outbox = Outbox(tmp_path / "outbox.sqlite3")
    with caplog.at_level(logging.WARNING, logger="bridgeos_agent"):
        before = fill(outbox)
        kept = [status(2), metrics(7), status(3)]
        for envelope in kept:
            outbox.put(envelope)
    assert outbox.disk_full
    said = [r.getMessage() for r in caplog.records if "disk full" in r.getMessage()]
    assert len(said) == 1, "the agent says so, once, not per frame"
    # Every frame is held, state events and the metric frame alike, in the order it was made.
    order = [e.id for e in (*before, *kept)]
    assert [frame_id for _, frame_id, _ in outbox.backlog()] == order
    assert all(outbox.held(frame_id) for frame_id in order)
    stats = outbox.stats()
    assert (stats.frames, stats.spilled_frames, stats.unstored_points, stats.spilled_points) == (len(order), 4, 0, 7)
    assert stats.spilled_bytes == sum(len(protocol.encode(e)) for e in (before[-1], *kept))
    assert outbox.evictions() == []
    assert outbox.frame(kept[1].id) == protocol.encode(kept[1])
    # Acks free the kept frames as they free stored ones.
    for envelope in kept[:2]:
        assert outbox.ack(envelope.id)
    assert [frame_id for _, frame_id, _ in outbox.backlog()] == [*order[:-3], kept[2].id]
    assert len(outbox) == len(order) - 2
    assert outbox.stats().spilled_bytes == sum(len(protocol.encode(e)) for e in (before[-1], kept[2]))


def test_past_the_memory_budget_the_oldest_metric_frames_go_first_and_their_points_are_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    frame = len(protocol.encode(metrics(5)))
    # Room for the state events and three metric frames, not four.
    budget = 3 * len(protocol.encode(status(1))) + 3 * frame + frame // 2
    outbox = Outbox(tmp_path / "outbox.sqlite3", memory_bytes=budget)
    with caplog.at_level(logging.WARNING, logger="bridgeos_agent"):
        before = fill(outbox)
        frames = [status(1), metrics(5), metrics(5), status(2), metrics(5)]
        for envelope in frames:
            outbox.put(envelope)
        assert outbox.evictions() == []
        assert not any("oldest metric frames" in r.getMessage() for r in caplog.records)
        newer = [metrics(5), metrics(5)]
        for envelope in newer:
            outbox.put(envelope)
    # The two oldest metric frames went, the newest are held; no state event was dropped.
    gone = [frames[1], frames[2]]
    assert [(frame_id, points) for frame_id, _, points in outbox.evictions()] == [(e.id, 5) for e in gone]
    assert outbox.evictions() == [], "told once"
    expected = [e.id for e in (*before, frames[0], frames[3], frames[4], *newer)]
    assert [frame_id for _, frame_id, _ in outbox.backlog()] == expected
    assert not any(outbox.held(e.id) for e in gone)
    stats = outbox.stats()
    assert (stats.unstored_points, stats.spilled_points) == (10, 25)
    assert stats.spilled_bytes <= budget
    warned = [r.getMessage() for r in caplog.records if "oldest metric frames" in r.getMessage()]
    assert len(warned) == 1, "the budget being spent is said once"
    # State events are kept past the budget: a flood of them drops every metric frame, never one of them.
    flood = [status(100 + n) for n in range(10)]
    for envelope in flood:
        outbox.put(envelope)
    assert all(outbox.held(e.id) for e in (*before, frames[0], frames[3], *flood))
    assert outbox.stats().spilled_bytes > budget
    assert {frame_id for frame_id, _, _ in outbox.evictions()} == {frames[4].id, newer[0].id, newer[1].id}
    # A metric frame that does not fit at all is not held, and counted, but not listed as evicted.
    late = metrics(3)
    outbox.put(late)
    assert not outbox.held(late.id)
    assert outbox.evictions() == []
    assert outbox.stats().unstored_points == 10 + 15 + 3


def test_a_negative_memory_budget_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="memory_bytes"):
        Outbox(tmp_path / "outbox.sqlite3", memory_bytes=-1)


def test_frames_stored_once_the_disk_has_room_again_come_after_the_ones_kept_in_memory(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    outbox = Outbox(tmp_path / "outbox.sqlite3")
    in_memory = fill(outbox)[-1]
    outbox._db.execute("PRAGMA max_page_count = 1073741823")
    with caplog.at_level(logging.WARNING, logger="bridgeos_agent"):
        later = status(3)
        outbox.put(later)
    assert not outbox.disk_full
    assert any("can write again" in r.getMessage() for r in caplog.records)
    assert [frame_id for _, frame_id, _ in outbox.backlog()][-2:] == [in_memory.id, later.id]
