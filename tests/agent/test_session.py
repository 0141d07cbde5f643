"""The robot's session over a real socket: a frame the cloud does not ack is sent again, with jitter, until acked."""

from __future__ import annotations

import asyncio
import contextlib
import time

import websockets

from bridgeos_agent import protocol
from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.protocol import Envelope, Event
from bridgeos_agent.session import RESEND_INITIAL


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

    async with websockets.serve(cloud, "127.0.0.1", 0) as server:
        port = server.sockets[0].getsockname()[1]
        settings = AgentSettings(
            master=f"ws://127.0.0.1:{port}",
            robot="sess-1",
            token="token",
            data_dir=tmp_path,
            simulate=True,
            detect_ros_master=False,
            volume_sync_interval=0,
        )
        controller = RobotController(settings, plugins={})
        running = asyncio.create_task(controller.run())
        try:
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
        finally:
            controller.stop()
            with contextlib.suppress(asyncio.CancelledError):
                await asyncio.wait_for(running, 15)
