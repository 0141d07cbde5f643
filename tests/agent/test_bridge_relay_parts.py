"""The bridge relay's pure parts: frames split into envelopes and put back, and the per-client byte budget."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridgeos_agent import protocol
from bridgeos_agent.bridges.relay import ByteBudget, FrameAssembler, frame_parts
from bridgeos_agent.protocol import BRIDGE_PART_CHARS, Event


@given(st.one_of(st.text(max_size=3 * BRIDGE_PART_CHARS // 1000), st.binary(max_size=1000)), st.integers(1, 400))
def test_a_frame_split_into_parts_comes_back_whole(frame, repeat) -> None:
    frame = frame * repeat
    assembler = FrameAssembler(1 << 30)
    parts = frame_parts("session-1", frame)
    out = None
    for data in parts:
        envelope = protocol.decode(protocol.encode(protocol.make(Event.BRIDGE_FRAME, data, now=0.0)))
        assert len(protocol.encode(envelope)) < protocol.MAX_FRAME_BYTES
        out = assembler.take(protocol.parse_payload(envelope))
    assert out == frame and type(out) is type(frame)


def test_a_frame_over_the_limit_is_refused_and_the_next_one_starts_clean() -> None:
    assembler = FrameAssembler(10)
    parts = [protocol.BridgeFrame(session="session-1", text="x" * 6, more=True)] * 2
    assembler.take(parts[0])
    with pytest.raises(ValueError, match="exceeds 10 bytes"):
        assembler.take(parts[1])
    assert assembler.take(protocol.BridgeFrame(session="session-1", text="ok")) == "ok"


def test_a_part_carries_exactly_one_of_text_and_binary() -> None:
    with pytest.raises(protocol.ProtocolError, match="exactly one of text and binary"):
        protocol.make(Event.BRIDGE_FRAME, {"session": "session-1"}, now=0.0)
    with pytest.raises(protocol.ProtocolError):
        protocol.make(Event.BRIDGE_OPEN, {"session": "x", "kind": "rosbridge"}, now=0.0)  # too short an id


def test_the_byte_budget_lets_a_burst_through_then_paces_at_its_rate() -> None:
    budget = ByteBudget(rate=1000, burst=1000, now=0.0)
    assert budget.delay(600, 0.0) == 0.0
    assert budget.delay(600, 0.0) == 0.0  # into debt: the next frame waits for it
    assert budget.delay(100, 0.0) == pytest.approx(0.2)
    assert budget.delay(100, 10.0) == 0.0  # refilled, never above the burst
    assert budget.tokens == 900
