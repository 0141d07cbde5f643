"""The outbox on a full disk: state events kept in order, metric points counted, never a crash."""

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


def test_state_events_on_a_full_disk_are_kept_in_order_and_metric_points_are_counted(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    outbox = Outbox(tmp_path / "outbox.sqlite3")
    with caplog.at_level(logging.WARNING, logger="bridgeos_agent"):
        before = fill(outbox)
        kept = [status(2), status(3)]
        outbox.put(kept[0])
        outbox.put(metrics(7))
        outbox.put(kept[1])
    assert outbox.disk_full
    said = [r.getMessage() for r in caplog.records if "disk full" in r.getMessage()]
    assert len(said) == 1, "the agent says so, once, not per frame"
    # Every state event is held, in the order it was made; the metric frame is not, its points are counted.
    order = [e.id for e in (*before, *kept)]
    assert [frame_id for _, frame_id, _ in outbox.backlog()] == order
    assert all(outbox.held(frame_id) for frame_id in order)
    stats = outbox.stats()
    assert (stats.frames, stats.spilled_frames, stats.unstored_points) == (len(order), 3, 7)
    assert outbox.frame(kept[0].id) == protocol.encode(kept[0])
    # Acks free the kept events as they free stored ones.
    assert outbox.ack(kept[0].id)
    assert kept[0].id not in [frame_id for _, frame_id, _ in outbox.backlog()]
    assert len(outbox) == len(order) - 1


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
