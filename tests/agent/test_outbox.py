"""The outbox keeps owed frames on disk, in order, bounded without ever dropping a state event."""

from __future__ import annotations

import asyncio
import time

import pytest

from bridgeos_agent import protocol
from bridgeos_agent.monitor import Reporter, SimulatedRobot
from bridgeos_agent.outbox import Outbox
from bridgeos_agent.protocol import Event
from bridgeos_agent.runtime import RestartPolicy
from bridgeos_agent.supervisor import SkillSupervisor


def metrics_frame(n: int, points: int = 10):
    return protocol.make(
        Event.METRICS,
        {"metrics": [{"name": "cpu", "value": float(i), "ts": float(n * 100 + i)} for i in range(points)]},
        now=time.time(),
    )


def status_frame(n: int):
    return protocol.make(Event.SKILL_STATUS, {"skill": f"skill-{n}", "status": "running"}, now=time.time())


def test_frames_survive_a_restart_in_order_until_acked(tmp_path):
    box = Outbox(tmp_path / "outbox.sqlite3")
    frames = [status_frame(0), metrics_frame(1), status_frame(2)]
    for frame in frames:
        box.put(frame)
    box.put(frames[1])  # a frame stored twice is held once
    box.close()
    reopened = Outbox(tmp_path / "outbox.sqlite3")
    assert [frame_id for _, frame_id, _ in reopened.backlog()] == [f.id for f in frames]
    assert reopened.ack(frames[1].id) and not reopened.ack(frames[1].id)
    assert [frame_id for _, frame_id, _ in reopened.backlog(batch=1)] == [frames[0].id, frames[2].id]
    assert protocol.decode(reopened.frame(frames[2].id)).id == frames[2].id
    assert reopened.frame(frames[1].id) is None
    assert reopened.stats().bytes == sum(len(protocol.encode(f)) for f in (frames[0], frames[2]))


def test_past_its_bound_old_metrics_are_thinned_and_state_events_kept(tmp_path):
    box = Outbox(tmp_path / "outbox.sqlite3", max_bytes=64 * 1024)
    states = []
    for n in range(400):
        box.put(metrics_frame(n))
        if n % 10 == 0:
            states.append(status_frame(n))
            box.put(states[-1])
    stats = box.stats()
    assert stats.bytes <= 64 * 1024
    assert stats.thinned_frames > 0
    held = {frame_id for _, frame_id, _ in box.backlog()}
    assert all(state.id in held for state in states), "a state event was dropped"
    # The newest metrics are kept whole; the thinning hits the oldest.
    newest = [protocol.decode(text) for _, _, text in box.backlog()][-5:]
    assert [f.data["metrics"][0]["ts"] for f in newest if f.event == Event.METRICS][-1] == 39900.0


def test_only_state_events_are_never_dropped_even_past_the_bound(tmp_path):
    box = Outbox(tmp_path / "outbox.sqlite3", max_bytes=1024)
    for n in range(50):
        box.put(status_frame(n))
    assert len(box) == 50


def test_an_outbox_smaller_than_a_frame_is_refused(tmp_path):
    with pytest.raises(ValueError, match="max_bytes"):
        Outbox(tmp_path / "o.sqlite3", max_bytes=10)


def test_the_reporter_sends_on_change_or_when_due():
    reporter = Reporter(max_interval=10.0, relative=0.05, absolute=0.5)
    assert [p["value"] for p in reporter.select(0.0, [("cpu", 50.0, None, None)])] == [50.0]
    assert reporter.select(1.0, [("cpu", 50.2, None, None)]) == []  # within 0.5 and 5 %
    assert [p["value"] for p in reporter.select(2.0, [("cpu", 60.0, None, None)])] == [60.0]
    assert reporter.select(11.0, [("cpu", 60.0, None, None)]) == []  # 9 s since the last send
    assert [p["ts"] for p in reporter.select(12.5, [("cpu", 60.0, None, None)])] == [12.5]
    points = reporter.select(13.0, [("cpu", 5.0, "s", "c")])
    assert points == [{"name": "cpu", "value": 5.0, "ts": 13.0, "skill": "s", "component": "c"}]
    reporter.forget("s")
    assert reporter.select(13.1, [("cpu", 5.0, "s", "c")]) != []


def test_a_simulated_robot_swings_its_bandwidth_and_drains_its_battery():
    robot = SimulatedRobot(cpu=2, ram=1024, bandwidth=100, bandwidth_min=10, period=100, seed=3)
    low, high = robot.bandwidth_now(75.0), robot.bandwidth_now(25.0)
    assert low == pytest.approx(10.0) and high == pytest.approx(100.0)
    first = robot.sample(0.0, {"cpu": 1.0, "ram": 512}, (0.0, 0.0))
    later = robot.sample(3600.0, {"cpu": 1.0, "ram": 512}, (0.0, 0.0))
    assert later.values["battery"] < first.values["battery"] == 100.0
    assert first.free["cpu"] == pytest.approx(2 - 1.0 - 0.1)
    assert first.free["ram"] == pytest.approx(1024 - 512 - 102.4)


def test_a_robot_config_below_the_simulated_low_point_caps_the_swing_at_its_peak():
    """The cloud's robot config sets the peak (apply_config); the swing never goes above it."""
    robot = SimulatedRobot(bandwidth=400, bandwidth_min=160, period=100)
    robot.bandwidth = 100.0
    assert max(robot.bandwidth_now(t) for t in range(100)) == pytest.approx(100.0)
    assert min(robot.bandwidth_now(t) for t in range(100)) == pytest.approx(100.0)


@pytest.mark.log_errors(r"skill s: router failed for good: boom")
async def test_a_crashing_plugin_restarts_with_backoff_then_gives_up():
    runs, failures = [], []

    async def flaky(supervisor):
        runs.append(time.monotonic())
        raise RuntimeError("boom")

    async def steady(supervisor):
        await asyncio.sleep(3600)

    policy = RestartPolicy(max_restarts=3, window=60, backoff_initial=0.01, backoff_max=0.05, jitter=0)
    supervisor = SkillSupervisor("s", policy=policy, on_failure=lambda name, why: failures.append((name, why)))
    supervisor.start("router", flaky)
    supervisor.start("manager", steady)
    for _ in range(100):
        if failures:
            break
        await asyncio.sleep(0.02)
    assert len(runs) == 4 and supervisor.restarts("router") == 3
    assert failures == [("router", "router crashed too often: boom")]
    assert supervisor.running("manager"), "one plug-in's crash leaves the others running"
    with pytest.raises(ValueError, match="runs already"):
        supervisor.start("manager", steady)
    await supervisor.close()
    assert not supervisor.running("manager")


def test_the_real_machine_is_read_per_interface():
    from bridgeos_agent.monitor import SystemRobot

    robot = SystemRobot(cpu=2, ram=1024)
    robot.sample(time.time(), {}, (0.0, 0.0))
    time.sleep(0.05)
    sample = robot.sample(time.time(), {"cpu": 0.5}, (10.0, 20.0))
    assert 0 <= sample.values["cpu"] <= 100 and 0 < sample.values["ram"] < 100
    assert sample.values["net_cloud_rx"] == 10.0 and sample.values["net_cloud_tx"] == 20.0
    assert all(v >= 0 for k, v in sample.values.items() if k.startswith(("net_rx:", "net_tx:")))
    assert not any(k.endswith(":lo") for k in sample.values)
    assert sample.free["cpu"] <= 2 - 0.5


def test_applied_frame_ids_survive_a_restart_bounded_to_the_newest(tmp_path):
    box = Outbox(tmp_path / "outbox.sqlite3")
    box.applied.kept = 300
    for n in range(1000):
        box.applied.add(f"cmd-{n}", f"answer-{n}")
    box.applied.add("cmd-999", "answer-999")  # answered again: still one row
    box.close()
    reopened = Outbox(tmp_path / "outbox.sqlite3")
    reopened.applied.kept = 300
    remembered = reopened.applied.load()
    assert remembered[-1] == ("cmd-999", "answer-999")
    assert [frame_id for frame_id, _ in remembered] == [f"cmd-{n}" for n in range(700, 1000)]
    # Trimmed every 200 additions: never more than kept + 200 rows on disk.
    assert 300 <= len(reopened.applied) <= 500
