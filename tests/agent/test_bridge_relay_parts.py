"""The bridge relay's pure parts: frames split into envelopes and put back, and the per-client byte budget."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from bridgeos_agent import protocol
from bridgeos_agent.bridges.relay import (
    BATCH_FRAME_BYTES,
    BridgeRelay,
    ByteBudget,
    FrameAssembler,
    _Session,
    frame_parts,
)
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
    with pytest.raises(protocol.ProtocolError, match="exactly one of text, binary and blob"):
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


async def sent_through(batches: bool, frames: list[str | bytes]) -> tuple[list[protocol.Envelope], list[str | bytes]]:
    """Write frames into one session as its engine would, in one go; return the envelopes and what the cloud rebuilds."""
    envelopes: list[protocol.Envelope] = []

    async def send_event(event: Event, data: dict) -> None:
        # Through the real encoder and decoder: every envelope is validated as on the link.
        envelopes.append(protocol.decode(protocol.encode(protocol.make(event, data, now=0.0))))

    async def no_graph():
        raise AssertionError("not needed")

    session = _Session(BridgeRelay(send_event, no_graph), "session-1", None, batches)
    for frame in frames:
        await session.send(frame)
    await session.flush()
    assembler, rebuilt = FrameAssembler(1 << 30), []
    for envelope in envelopes:
        out = assembler.take(protocol.parse_payload(envelope))
        rebuilt += out if isinstance(out, list) else [] if out is None else [out]
    return envelopes, rebuilt


async def test_frames_written_in_one_go_cross_the_link_as_batches_in_order() -> None:
    frames: list[str | bytes] = [f"message {i}" for i in range(500)]
    frames += [b"\x01binary" + bytes([i]) for i in range(100)]  # a type change starts a new batch
    frames += ["x" * (BATCH_FRAME_BYTES + 1)]  # too big to batch: goes alone, after what came before
    frames += [f"after {i}" for i in range(10)]
    envelopes, rebuilt = await sent_through(True, frames)
    assert rebuilt == frames
    assert len(envelopes) <= 5
    payloads = [protocol.parse_payload(e) for e in envelopes]
    assert payloads[0].texts is not None and payloads[1].binaries is not None


async def test_a_cloud_that_did_not_ask_for_batches_gets_one_envelope_per_frame() -> None:
    frames: list[str | bytes] = [f"message {i}" for i in range(20)] + [b"\x01bin"]
    envelopes, rebuilt = await sent_through(False, frames)
    assert rebuilt == frames and len(envelopes) == len(frames)
    assert all(protocol.parse_payload(e).texts is None for e in envelopes)


def test_a_batch_carries_whole_frames_within_one_parts_size() -> None:
    with pytest.raises(protocol.ProtocolError, match="whole frames only"):
        protocol.make(Event.BRIDGE_FRAME, {"session": "session-1", "texts": ["a"], "more": True}, now=0.0)
    with pytest.raises(protocol.ProtocolError, match="at most"):
        protocol.make(Event.BRIDGE_FRAME, {"session": "session-1", "texts": ["x" * BRIDGE_PART_CHARS, "y"]}, now=0.0)
    with pytest.raises(protocol.ProtocolError, match="exactly one"):
        protocol.make(Event.BRIDGE_FRAME, {"session": "session-1", "text": "a", "texts": ["b"]}, now=0.0)
