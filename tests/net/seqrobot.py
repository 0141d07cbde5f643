"""`bridgeos-agent run` with a counter: a metric `seq` = 0, 1, 2, … every 50 ms, to prove none is lost.

Run like the agent (same options). On SIGTERM it stops counting, waits until the cloud acked
every frame (the outbox is empty), then stops the agent.
"""

from __future__ import annotations

import asyncio
import signal
import sys
import time

from bridgeos_agent.agent import settings_from_args
from bridgeos_agent.cli import build_parser
from bridgeos_agent.controller import RobotController
from bridgeos_agent.protocol import Event


async def main(argv: list[str]) -> int:
    args = build_parser().parse_args(argv)
    controller = RobotController(settings_from_args(args), say=lambda line: print(line, flush=True))
    stopping = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, stopping.set)
    running = loop.create_task(controller.run())

    async def count() -> None:
        await controller.connected.wait()
        n = 0
        while not stopping.is_set():
            await controller.emit(Event.METRICS, {"metrics": [{"name": "seq", "value": n, "ts": time.time()}]})
            n += 1
            await asyncio.sleep(0.05)
        print(f"counted to {n - 1}", flush=True)

    counter = loop.create_task(count())
    await stopping.wait()
    await counter
    deadline = time.monotonic() + 45
    while len(controller.outbox) and time.monotonic() < deadline:
        await asyncio.sleep(0.1)
    print(f"outbox: {len(controller.outbox)} frame(s) unacked", flush=True)
    controller.stop()
    return await running


if __name__ == "__main__":
    sys.exit(asyncio.run(main(sys.argv[1:])))
