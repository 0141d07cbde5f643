"""The robot's session over a real socket: a frame the cloud does not ack is sent again, with jitter, until acked."""

from __future__ import annotations

import asyncio
import contextlib
import sqlite3
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import websockets

from bridgeos_agent import protocol
from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.protocol import Envelope, Event
from bridgeos_agent.session import RESEND_INITIAL


@contextlib.asynccontextmanager
async def running_agent(cloud: Any, robot: str, tmp_path: Path) -> AsyncIterator[tuple[RobotController, asyncio.Task]]:
    """Run a simulated agent against ``cloud`` (a websockets handler) on a port of its own; stop it at the end."""
    async with websockets.serve(cloud, "127.0.0.1", 0) as server:
        port = server.sockets[0].getsockname()[1]
        settings = AgentSettings(
            master=f"ws://127.0.0.1:{port}",
            robot=robot,
            token="token",
            data_dir=tmp_path,
            simulate=True,
            detect_ros_master=False,
            volume_sync_interval=0,
        )
        controller = RobotController(settings, plugins={})
        running = asyncio.create_task(controller.run())
        try:
            yield controller, running
        finally:
            controller.stop()
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait_for(running, 15)


async def test_an_unacked_frame_is_sent_again_after_its_backoff_and_dropped_once_acked(tmp_path):
    received: list[tuple[float, Envelope]] = []  # every component_status the cloud got, when
    acked = asyncio.Event()

    async def cloud(ws):
        protocol.decode(await ws.recv())  # authentication_robot
        await ws.send(
            protocol.encode(protocol.make(Event.AUTHENTICATION_SUCCESS, {"robot": "sess-1"}, now=time.time()))
        )
        async for raw in ws:
            envelope = protocol.decode(raw)
            if envelope.event == Event.COMPONENT_STATUS:
                received.append((time.monotonic(), envelope))
                if len(received) == 1:
                    continue  # the first copy is "lost": no ack
                acked.set()
            if envelope.event in protocol.REQUIRES_ACK:
                await ws.send(protocol.ack_text(envelope.id, now=time.time()))

    async with running_agent(cloud, "sess-1", tmp_path) as (controller, _):
        await asyncio.wait_for(controller.connected.wait(), 10)
        sent = await controller.emit(
            Event.COMPONENT_STATUS, {"skill": "nav", "component": "planner", "status": "running"}
        )
        await asyncio.wait_for(acked.wait(), RESEND_INITIAL * 2)
        await asyncio.sleep(0.2)  # the ack crosses back
        (first_at, first), (again_at, again) = received
        assert first.id == again.id == sent.id
        # Reliable's first delay, within its ±10 % jitter (and the 0.5 s tick that sends what is due).
        assert RESEND_INITIAL * 0.9 - 0.05 <= again_at - first_at <= RESEND_INITIAL * 1.1 + 0.6
        assert sent.id not in controller.outbox
        assert len(controller.session.reliable) == 0


async def test_a_command_is_answered_even_when_its_id_cannot_be_kept_on_disk(tmp_path, caplog):
    answers: dict[str, Envelope] = {}
    connected = asyncio.Event()
    cloud_ws = []

    async def cloud(ws):
        protocol.decode(await ws.recv())  # authentication_robot
        await ws.send(
            protocol.encode(protocol.make(Event.AUTHENTICATION_SUCCESS, {"robot": "sess-2"}, now=time.time()))
        )
        cloud_ws.append(ws)
        connected.set()
        async for raw in ws:
            envelope = protocol.decode(raw)
            if envelope.reply_to:
                answers[envelope.reply_to] = envelope

    async with running_agent(cloud, "sess-2", tmp_path) as (controller, _):
        await asyncio.wait_for(connected.wait(), 10)
        kept = protocol.make(Event.OFFLOADING, {"mode": "manual"}, now=time.time())
        await cloud_ws[0].send(protocol.encode(kept))
        await asyncio.wait_for(_answered(answers, kept.id), 5)
        # The outbox's file refuses writes now (as a full disk would): the answer still comes.
        db: sqlite3.Connection = controller.outbox._db
        db.execute("PRAGMA query_only=ON")
        try:
            lost = protocol.make(Event.OFFLOADING, {"mode": "auto"}, now=time.time())
            await cloud_ws[0].send(protocol.encode(lost))
            await asyncio.wait_for(_answered(answers, lost.id), 10)
        finally:
            db.execute("PRAGMA query_only=OFF")
        assert answers[lost.id].event == Event.ACK
        assert "keeping an applied command's id on disk failed" in caplog.text
        remembered = [frame_id for frame_id, _ in controller.outbox.applied.load()]
        assert kept.id in remembered and lost.id not in remembered


async def _answered(answers: dict[str, Envelope], frame_id: str) -> None:
    while frame_id not in answers:
        await asyncio.sleep(0.02)


async def test_on_a_full_disk_metric_frames_wait_in_memory_and_past_the_budget_the_oldest_are_counted_dropped(
    tmp_path,
):
    points: dict[str, int] = {}  # metric frame id -> points the cloud got
    order: list[str] = []

    async def cloud(ws):
        protocol.decode(await ws.recv())  # authentication_robot
        await ws.send(
            protocol.encode(protocol.make(Event.AUTHENTICATION_SUCCESS, {"robot": "sess-3"}, now=time.time()))
        )
        async for raw in ws:
            envelope = protocol.decode(raw)
            if envelope.event == Event.METRICS:
                points[envelope.id] = len(envelope.data["metrics"])
                order.append(envelope.id)
            if envelope.event in protocol.REQUIRES_ACK:
                await ws.send(protocol.ack_text(envelope.id, now=time.time()))

    def frame(n: int) -> dict:
        return {"metrics": [{"name": "cpu", "value": float(i), "ts": 1000.0 + n} for i in range(5)]}

    size = len(protocol.encode(protocol.make(Event.METRICS, frame(0), now=time.time())))
    async with websockets.serve(cloud, "127.0.0.1", 0) as server:
        port = server.sockets[0].getsockname()[1]
        settings = AgentSettings(
            master=f"ws://127.0.0.1:{port}",
            robot="sess-3",
            token="token",
            data_dir=tmp_path,
            simulate=True,
            sample_interval=3600,
            detect_ros_master=False,
            volume_sync_interval=0,
            outbox_memory_bytes=1 << 20,
        )
        controller = RobotController(settings, plugins={})
        session = controller.session
        outbox = controller.outbox
        assert outbox.memory_bytes == 1 << 20
        # The disk is full (the file cannot grow) and the cloud is not reached yet.
        pages = outbox._db.execute("PRAGMA page_count").fetchone()[0]
        outbox._db.execute(f"PRAGMA max_page_count = {pages}")
        while not outbox.disk_full:
            await session.emit(Event.COMPONENT_STATUS, {"skill": "s", "component": "c", "status": "running"})
        outbox.memory_bytes = outbox.stats().spilled_bytes + 3 * size + size // 2  # three metric frames, not four
        emitted = [await session.emit(Event.METRICS, frame(n)) for n in range(8)]
        # The newest three are held in memory; the five before went, oldest first, counted as dropped.
        assert [outbox.held(e.id) for e in emitted] == [False] * 5 + [True] * 3
        assert session.metric_points_dropped == outbox.unstored_points == 25
        running = asyncio.create_task(controller.run())
        try:
            await asyncio.wait_for(controller.connected.wait(), 10)
            deadline = time.monotonic() + 10
            while (len(outbox) or session.unstored_in_flight) and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            assert len(outbox) == 0 and session.unstored_in_flight == 0
            # Resent on reconnect, in order; every point the agent made reached the cloud or was counted dropped.
            kept = [e.id for e in emitted[5:]]
            assert [frame_id for frame_id in order if frame_id in kept] == kept
            assert not any(e.id in points for e in emitted[:5])
            assert session.metric_points_sent == sum(points.values()) + session.metric_points_dropped
        finally:
            controller.stop()
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait_for(running, 15)


async def test_a_frame_made_while_the_backlog_is_being_resent_is_sent_on_that_connection(tmp_path):
    received: list[str] = []  # ids of the component_status frames the cloud got

    async def cloud(ws):
        protocol.decode(await ws.recv())  # authentication_robot
        await ws.send(
            protocol.encode(protocol.make(Event.AUTHENTICATION_SUCCESS, {"robot": "sess-4"}, now=time.time()))
        )
        async for raw in ws:
            envelope = protocol.decode(raw)
            if envelope.event == Event.COMPONENT_STATUS:
                received.append(envelope.id)
            if envelope.event in protocol.REQUIRES_ACK:
                await ws.send(protocol.ack_text(envelope.id, now=time.time()))

    def status(n: int) -> dict:
        return {"skill": "nav", "component": f"c{n}", "status": "running"}

    async with websockets.serve(cloud, "127.0.0.1", 0) as server:
        port = server.sockets[0].getsockname()[1]
        settings = AgentSettings(
            master=f"ws://127.0.0.1:{port}",
            robot="sess-4",
            token="token",
            data_dir=tmp_path,
            simulate=True,
            sample_interval=3600,
            detect_ros_master=False,
            volume_sync_interval=0,
        )
        controller = RobotController(settings, plugins={})
        outbox = controller.outbox
        # A backlog made while the cloud was out of reach.
        owed = [await controller.session.emit(Event.COMPONENT_STATUS, status(n)) for n in range(5)]
        late: list[str] = []
        original = outbox.backlog

        def backlog(**kw):
            rows = list(original(**kw))  # every read of the file done, as when the last page came short
            yield from rows[:1]
            if not late:
                # A frame made while the replay is under way (e.g. the revert stopping a local copy).
                made = protocol.make(Event.COMPONENT_STATUS, status(99), now=time.time())
                outbox.put(made)
                late.append(made.id)
            yield from rows[1:]

        outbox.backlog = backlog  # type: ignore[method-assign]
        running = asyncio.create_task(controller.run())
        try:
            await asyncio.wait_for(controller.connected.wait(), 10)
            deadline = time.monotonic() + 5
            while len(outbox) and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            # Sent on this connection, after the backlog it was made during: not left for the next one.
            assert received == [e.id for e in owed] + late
            assert len(outbox) == 0
        finally:
            controller.stop()
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait_for(running, 15)


async def test_a_login_the_cloud_leaves_unanswered_is_tried_again_not_given_up(tmp_path, monkeypatch):
    # In a connect storm of thousands the cloud may take the socket and answer the login late; a
    # robot that gave up waiting used to stop trying for good (found with 2,000 robots and a real agent).
    monkeypatch.setattr("bridgeos_agent.session.LOGIN_ANSWER_S", 0.5)
    logins: list[float] = []

    async def cloud(ws):
        protocol.decode(await ws.recv())  # authentication_robot
        logins.append(time.monotonic())
        if len(logins) == 1:
            await asyncio.sleep(3)  # the first login is never answered in time
            return
        await ws.send(
            protocol.encode(protocol.make(Event.AUTHENTICATION_SUCCESS, {"robot": "sess-3"}, now=time.time()))
        )
        async for _ in ws:
            pass

    async with running_agent(cloud, "sess-3", tmp_path) as (controller, running):
        await asyncio.wait_for(controller.connected.wait(), 15)
        assert len(logins) == 2
        assert not running.done()
