"""Simulated robots for fleet benchmarks: many robots per process over the real wire protocol, one asyncio loop.

Each robot authenticates with its own token on /ws/robot/, acks what the cloud sends, and answers
Skill orders as a Robot Controller does, without running anything: ``skill_stop`` reports its
components and the Skill stopped, ``skill_start`` reports them running on the robot. A Skill
whose name says ``crash`` reports a component crash (failed, then restarting) soon after it starts,
as a component that dies does. A robot told to come back ``restarted`` asks the cloud for its
Skills' configs and starts them, as a controller restarting after a power cut does. The real
agent stays the reference for behaviour: tests/rollouts drives real ones.
"""

from __future__ import annotations

import asyncio
import json
import time
import uuid
from typing import Any

from bridgeos_agent.protocol import COMMANDS, REQUIRES_ACK

NEEDS_ACK = {str(event) for event in REQUIRES_ACK | COMMANDS}
CRASH_AFTER_S = 0.5


class SimRobot:
    """One simulated robot on one WebSocket."""

    def __init__(self, url: str, robot_id: str, token: str, skills: dict[str, dict[str, Any]]) -> None:
        self.url, self.robot_id, self.token = url, robot_id, token
        # What runs: skill id -> its config (as started).
        self.skills = skills
        self.ws: Any = None
        self.connected = asyncio.Event()

    async def send(self, event: str, data: dict[str, Any], reply_to: str | None = None) -> str:
        frame_id = uuid.uuid4().hex
        frame = {"event": event, "id": frame_id, "reply_to": reply_to, "data": data, "ts": time.time()}
        await self.ws.send(json.dumps(frame))
        return frame_id

    async def run(self, stop: asyncio.Event, *, restarted: bool = False) -> None:
        """Stay connected until ``stop``; a restarted robot starts its Skills again with the cloud's configs."""
        from websockets.asyncio.client import connect

        async with connect(self.url, compression=None, ping_interval=None, open_timeout=60, max_size=2**23) as ws:
            self.ws = ws
            await self.send("authentication_robot", {"robot": self.robot_id, "token": self.token})
            reader = asyncio.ensure_future(self._read(restarted))
            stopping = asyncio.ensure_future(stop.wait())
            await asyncio.wait({reader, stopping}, return_when=asyncio.FIRST_COMPLETED)
            reader.cancel()
            stopping.cancel()

    async def _read(self, restarted: bool) -> None:
        pending: dict[str, str] = {}  # request id -> skill id, for configs asked at a restart
        async for raw in self.ws:
            frame = json.loads(raw)
            event, data = frame["event"], frame.get("data") or {}
            if event in NEEDS_ACK and frame.get("reply_to") is None:
                await self.send("ack", {}, reply_to=frame["id"])
            if event == "authentication_success":
                self.connected.set()
                if restarted:
                    for skill_id in list(self.skills):
                        pending[await self.send("skill_config_get", {"skill": skill_id})] = skill_id
            elif event == "skill_config" and frame.get("reply_to") in pending:
                pending.pop(frame["reply_to"])
                await self.start(data["config"])
            elif event == "skill_start":
                config = data.get("config") or self.skills.get(data["skill"])
                if config is not None:
                    await self.start(config)
            elif event == "skill_stop":
                await self.stop(data["skill"])

    async def start(self, config: dict[str, Any]) -> None:
        skill_id = config["skill_id"]
        self.skills[skill_id] = config
        await self.send("skill_status", {"skill": skill_id, "status": "starting"})
        for component in config["components"]:
            await self.send(
                "component_status",
                {"skill": skill_id, "component": component, "status": "running", "location": "robot"},
            )
        await self.send("skill_status", {"skill": skill_id, "status": "running"})
        if "crash" in config["skill"].lower():
            asyncio.get_running_loop().call_later(CRASH_AFTER_S, lambda: asyncio.ensure_future(self.crash(config)))

    async def crash(self, config: dict[str, Any]) -> None:
        skill_id = config["skill_id"]
        if self.skills.get(skill_id) is not config:
            return  # replaced since
        component = next(iter(config["components"]))
        message = "crashed (exit code 3); restart 0"
        await self.send(
            "component_status", {"skill": skill_id, "component": component, "status": "failed", "message": message}
        )
        await self.send(
            "component_status", {"skill": skill_id, "component": component, "status": "running", "location": "robot"}
        )

    async def stop(self, skill_id: str) -> None:
        config = self.skills.get(skill_id)
        await self.send("skill_status", {"skill": skill_id, "status": "stopping"})
        for component in (config or {}).get("components", {}):
            await self.send("component_status", {"skill": skill_id, "component": component, "status": "stopped"})
        await self.send("skill_status", {"skill": skill_id, "status": "stopped"})


def fleet_worker(
    index: int,
    robots: list[tuple[str, str]],
    start_event: Any,
    stop_event: Any,
    results: Any,
    url: str,
    skill: dict[str, Any],
    connected: Any,
) -> None:
    """Run a share of the fleet in a process of its own until told to stop; report how many connected."""

    async def run() -> int:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        loop.run_in_executor(None, stop_event.wait).add_done_callback(lambda _: loop.call_soon_threadsafe(stop.set))
        sims = [SimRobot(url, robot_id, token, {skill["skill_id"]: skill}) for robot_id, token in robots]
        tasks = [asyncio.ensure_future(sim.run(stop)) for sim in sims]
        await asyncio.gather(*(sim.connected.wait() for sim in sims))
        with connected.get_lock():
            connected.value += len(sims)
        await asyncio.gather(*tasks, return_exceptions=True)
        return len(sims)

    results.put(asyncio.run(run()))
