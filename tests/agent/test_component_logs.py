"""Component logs on the robot: level parsing, the on-disk ring, and capture from real processes."""

from __future__ import annotations

import asyncio
import json
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from bridgeos_agent import protocol
from bridgeos_agent.logs.capture import CUT_MARK, FileTail, parse_level, split_lines
from bridgeos_agent.logs.ring import LogRing
from bridgeos_agent.logs.service import ComponentLogService
from bridgeos_agent.logs.shipper import encode_frame, frame_data
from bridgeos_agent.protocol import MAX_LOG_LINE_CHARS, LogLine
from bridgeos_agent.robotconfig import LogsPolicy, parse_robot_config
from bridgeos_agent.runtime import ComponentSpec, ProcessRuntime
from bridgeos_agent.skillconfig import ComponentResources, LaunchSpec
from tests.conftest import eventually

ROBOT = "logs-robot-1"


@pytest.mark.parametrize(
    ("line", "level"),
    [
        ("[INFO] [1700000000.123]: started", "info"),
        ("[ WARN] [1700000000.123]: slow", "warning"),
        ("[ERROR] [1700000000.123] [talker]: lost", "error"),
        ("[DEBUG] [1700000000.1] [n]: x", "debug"),
        ("[FATAL] [1700000000.1] [n]: x", "critical"),
        ("[talker-1] [WARN] [1700000000.1] [talker]: x", "warning"),
        ("\x1b[33m[ WARN] [1700000000.1]: coloured", "warning"),
        ("WARNING:root:disk almost full", "warning"),
        ("ERROR:detector:no camera", "error"),
        ("CRITICAL:x:y", "critical"),
        ("2026-12-04 19:00:00,123 - detector - ERROR - no camera", "error"),
        ("2026-12-04 19:00:00,123 - detector - INFO - ready", "info"),
        ('{"level": "warn", "msg": "x"}', "warning"),
        ('{"levelname": "ERROR", "message": "x"}', "error"),
        ('{"severity": "CRITICAL"}', "critical"),
        ('{"level": 40}', "error"),
        ('{"msg": "no level"}', None),
        ("{not json", None),
        ("plain output 42", None),
        ("an INFO word inside", None),
        ("", None),
    ],
)
def test_a_lines_level_is_read_from_ros_python_logging_and_json(line: str, level: str | None) -> None:
    assert parse_level(line) == level


def test_a_long_line_is_cut_and_says_so() -> None:
    lines, used = split_lines(b"short\n" + b"x" * (MAX_LOG_LINE_CHARS + 500) + b"\npartial")

    assert lines[0] == "short"
    assert len(lines[1]) == MAX_LOG_LINE_CHARS and lines[1].endswith(CUT_MARK)
    assert used == len(b"short\n") + MAX_LOG_LINE_CHARS + 501  # the partial last line waits for its newline
    LogLine(seq=1, ts=1.0, stream="stdout", text=lines[1])  # fits the protocol


def test_a_ring_numbers_lines_stays_in_its_size_and_survives_a_reload(tmp_path: Path) -> None:
    ring = LogRing(tmp_path / "ring", max_bytes=64 * 1024)
    for batch in range(100):
        ring.append([(1.0 + batch, "stdout", "info", f"line {batch}-{i} " + "x" * 40) for i in range(50)])
    ring.mark_shipped(4000)

    on_disk = sum(path.stat().st_size for path in (tmp_path / "ring").glob("*.seg"))
    assert on_disk <= 64 * 1024
    assert ring.seq == 5000
    assert ring.first > 1  # the oldest lines went, oldest first
    again = LogRing(tmp_path / "ring", max_bytes=64 * 1024)
    assert (again.seq, again.shipped, again.first) == (5000, 4000, ring.first)
    seqs = [line[0] for line in again.lines_after(0, 10_000)]
    assert seqs == list(range(again.first, 5001))
    assert again.lines_after(4990, 3) == ring.lines_after(4990, 3)
    assert again.append([(9.0, "stderr", None, "next")]) == 5001
    assert again.last(1) == [(5001, 9.0, "stderr", None, "next")]


def test_a_ring_drops_a_line_torn_by_a_crash_mid_write(tmp_path: Path) -> None:
    ring = LogRing(tmp_path / "ring", max_bytes=1024 * 1024)
    ring.append([(1.0, "stdout", None, "one"), (1.0, "stdout", None, "two")])
    segment = next((tmp_path / "ring").glob("*.seg"))
    with segment.open("ab") as file:
        file.write(b"3\t1.0\to\t-\tthr")  # the agent died in the middle of this write
    (tmp_path / "ring" / "state.json").unlink()

    again = LogRing(tmp_path / "ring", max_bytes=1024 * 1024)

    assert again.seq == 2
    assert [line[4] for line in again.lines_after(0, 10)] == ["one", "two"]


def spec(component: str, code: str, *, skill: str = "chatty") -> ComponentSpec:
    return ComponentSpec(
        robot=ROBOT,
        skill=skill,
        component=component,
        location="robot",
        launch=LaunchSpec(command=[sys.executable, "-c", code]),
        resources=ComponentResources(),
        env={},
    )


class NoLink:
    """A session that never connects: these tests look at capture only."""

    ws = None

    def idle(self, max_buffered: int) -> bool:
        return False


@pytest.fixture
async def runtime(tmp_path: Path) -> AsyncIterator[ProcessRuntime]:
    runtime = ProcessRuntime(ROBOT, data_dir=tmp_path / "runtime")
    yield runtime
    await runtime.close(stop_components=True)


async def running(service: ComponentLogService) -> asyncio.Task[None]:
    return asyncio.create_task(service.run())


async def stop(task: asyncio.Task[None]) -> None:
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)


async def test_a_process_components_stdout_and_stderr_reach_its_ring_with_streams_and_levels(
    runtime: ProcessRuntime, tmp_path: Path
) -> None:
    service = ComponentLogService(tmp_path / "logs", runtime, NoLink())  # type: ignore[arg-type]
    task = await running(service)
    try:
        code = (
            "import sys, json, time, logging\n"
            "print('[INFO] [1.0]: node up', flush=True)\n"
            "logging.basicConfig(); logging.warning('low battery')\n"
            "print(json.dumps({'level': 'error', 'msg': 'no lidar'}), flush=True)\n"
            "print('x' * 20000, flush=True)\n"
            "time.sleep(3600)"
        )
        await runtime.start(spec("driver", code))
        ring = service.rings.get("chatty", "driver")
        assert ring is not None
        lines = await eventually(lambda: ring.seq >= 4 and ring.lines_after(0, 10), timeout=10, what="4 lines")
    finally:
        await stop(task)

    by_text = {text[:40]: (stream, level) for _, _, stream, level, text in lines}
    assert by_text["[INFO] [1.0]: node up"] == ("stdout", "info")
    assert by_text["WARNING:root:low battery"] == ("stderr", "warning")
    assert by_text['{"level": "error", "msg": "no lidar"}'] == ("stdout", "error")
    long = next(text for *_, text in lines if text.startswith("xxx"))
    assert len(long) == MAX_LOG_LINE_CHARS and long.endswith(CUT_MARK)
    assert all(abs(ts - time.time()) < 30 for _, ts, *_ in lines)
    # The runtime's own logs() now reads the ring: both streams in the order captured.
    assert "WARNING:root:low battery" in await runtime.logs("chatty", "driver", 10)


async def test_lines_printed_while_the_agent_was_down_are_captured_once_after_its_restart(tmp_path: Path) -> None:
    code = "import time\ni = 0\nwhile True:\n    i += 1\n    print(f'tick {i}', flush=True)\n    time.sleep(0.01)"
    first = ProcessRuntime(ROBOT, data_dir=tmp_path / "runtime")
    service = ComponentLogService(tmp_path / "logs", first, NoLink())  # type: ignore[arg-type]
    task = await running(service)
    await first.start(spec("ticker", code))
    ring = service.rings.get("chatty", "ticker")
    assert ring is not None
    await eventually(lambda: ring.seq >= 20, timeout=10, what="20 ticks")
    await stop(task)
    saved = first.get_state()
    await first.close()  # the agent stops; the component keeps printing
    await asyncio.sleep(0.5)

    second = ProcessRuntime(ROBOT, data_dir=tmp_path / "runtime")
    try:
        assert [s.component for s in await second.load_state(saved)] == ["ticker"]
        restarted = ComponentLogService(tmp_path / "logs", second, NoLink())  # type: ignore[arg-type]
        task = await running(restarted)
        again = restarted.rings.get("chatty", "ticker")
        assert again is not None
        await eventually(lambda: again.seq >= ring.seq + 60, timeout=10, what="ticks after the restart")
        await stop(task)
    finally:
        await second.close(stop_components=True)

    texts = [line[4] for line in again.lines_after(0, 100_000)]
    seqs = [line[0] for line in again.lines_after(0, 100_000)]
    assert seqs == list(range(1, len(seqs) + 1))
    assert texts == [f"tick {i}" for i in range(1, len(texts) + 1)]  # none lost, none twice


async def test_a_flood_keeps_its_file_small_loses_no_line_and_leaves_the_event_loop_free(tmp_path: Path) -> None:
    runtime = ProcessRuntime(ROBOT, data_dir=tmp_path / "runtime", log_max_bytes=256 * 1024)
    service = ComponentLogService(
        tmp_path / "logs",
        runtime,
        NoLink(),
        LogsPolicy(ring_bytes=64 * 1024 * 1024),  # type: ignore[arg-type]
    )
    task = await running(service)
    lags: list[float] = []

    async def ticker() -> None:
        while True:
            before = time.monotonic()
            await asyncio.sleep(0.01)
            lags.append(time.monotonic() - before - 0.01)

    ticking = asyncio.create_task(ticker())
    count = 200_000  # at ~50,000 lines/s and more: as fast as Python prints
    code = f"import sys, time\nfor i in range({count}): sys.stdout.write(f'line {{i}}\\n')\nsys.stdout.flush()\ntime.sleep(3600)"
    try:
        await runtime.start(spec("flood", code))
        ring = service.rings.get("chatty", "flood")
        assert ring is not None
        started = time.monotonic()
        await eventually(lambda: ring.seq >= count, timeout=30, what="every line in the ring")
        elapsed = time.monotonic() - started
    finally:
        ticking.cancel()
        await stop(task)
        await runtime.close(stop_components=True)

    texts = [line[4] for line in ring.lines_after(0, count + 10)]
    assert texts == [f"line {i}" for i in range(count)]
    assert runtime.log_path("chatty", "flood").stat().st_blocks * 512 <= 2 * 256 * 1024  # read parts given back
    assert count / elapsed > 20_000, f"captured {count / elapsed:.0f} lines/s"
    lags.sort()
    print(f"event loop lag p50 {lags[len(lags) // 2] * 1000:.1f} ms, p95 {lags[int(len(lags) * 0.95)] * 1000:.1f} ms")
    assert lags[int(len(lags) * 0.95)] < 0.05, f"event loop p95 lag {lags[int(len(lags) * 0.95)]:.3f} s"


def test_the_robot_config_has_a_logs_section_with_its_defaults_and_limits() -> None:
    config = parse_robot_config({})
    assert config.logs == LogsPolicy(
        enabled=True, ring_bytes=8 * 1024 * 1024, rate_lines_per_s=25_000, rate_bytes_per_s=4 * 1024 * 1024
    )
    with pytest.raises(ValueError, match=r"logs\.ring_bytes"):
        parse_robot_config({"logs": {"ring_bytes": 10}})
    with pytest.raises(ValueError, match=r"logs\.rate_lines_per_s"):
        parse_robot_config(json.dumps({"logs": {"rate_lines_per_s": 0}}))


def test_a_file_tail_finishes_a_file_moved_aside_at_a_relaunch(tmp_path: Path) -> None:
    out = tmp_path / "c.log"
    out.write_bytes(b"one\ntwo\n")
    tail = FileTail({"stdout": out}, max_bytes=1 << 20, clock=lambda: 5.0)
    found, position = tail.read(None)
    with out.open("ab") as file:
        file.write(b"three\n")
    out.rename(tmp_path / "c.log.1")  # the runtime's rotation before a relaunch
    out.write_bytes(b"four\n")

    more, _ = tail.read(position)

    assert [entry[3] for entry in found + more] == ["one", "two", "three", "four"]
    assert found[0] == (5.0, "stdout", None, "one")


def test_a_log_frame_is_a_valid_component_logs_frame_from_a_robot() -> None:
    lines = [
        (seq, 1_800_000_000.5, "stderr", None if seq % 2 else "error", f'say "{seq}"\t\x1b') for seq in range(7, 12)
    ]

    frame_id, text = encode_frame(frame_data("chatty", "driver", lines, dropped=6), now=1_800_000_001.0)

    envelope = protocol.decode(text, direction=protocol.Direction.ROBOT_TO_CLOUD)
    assert (envelope.id, envelope.event, envelope.reply_to) == (frame_id, "component_logs", None)
    payload = protocol.parse_payload(envelope)
    assert (payload.skill, payload.component, payload.location, payload.dropped) == ("chatty", "driver", "robot", 6)
    assert [(line.seq, line.stream, line.level, line.text) for line in payload.lines] == [
        (seq, stream, level, text) for seq, _, stream, level, text in lines
    ]


def test_output_far_ahead_of_the_reads_is_passed_over_counted_and_the_ring_ships_the_gap_as_dropped(
    tmp_path: Path,
) -> None:
    out = tmp_path / "c.log"
    total = 200_000  # about 2.3 MB unread: over the ring's 1 MiB
    out.write_bytes("".join(f"line {n}\n" for n in range(1, total + 1)).encode())
    tail = FileTail({"stdout": out}, max_bytes=64 * 1024)
    ring = LogRing(tmp_path / "ring", max_bytes=1 << 20)
    tail.keep_bytes = ring.max_bytes
    ring.append([(1.0, "stdout", None, "before")])  # seq 1, shipped below

    taken: list[str] = []
    position = None
    for _ in range(50):
        found, position = tail.read(position)
        ring.skip(tail.take_skipped())
        ring.append(found, position)
        taken += [entry[3] for entry in found]
        if not found:
            break

    skipped = total - len(taken)
    # Oldest first: what was passed over is the start, what was read is the end, in order.
    assert skipped > 0 and taken == [f"line {n}" for n in range(skipped + 1, total + 1)]
    assert ring.seq == 1 + total
    after = ring.lines_after(1, 10)
    assert after[0][0] == 2 + skipped and after[0][4] == f"line {skipped + 1}"
    # A frame from the cursor starts after the gap: its `dropped` is the lines passed over.
    data = frame_data("s", "c", after)
    assert after[0][0] - 1 - 1 == skipped and data["lines"][0]["seq"] == 2 + skipped
