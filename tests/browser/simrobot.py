"""Simulated robots for what the real agent does not do yet: the reference Link playing a robot.

The browser tests play a robot with the real agent (`bridgeos-agent run --simulate`, started
by `start_agent` in conftest.py) wherever it can. This simulator stays for two things: a
steady stream of Skill Manager decisions to stay (the `offloading.decision` metric, which a
real manager sends only where a policy has costs to compare), and fleets of hundreds of robots
in one process (benchmarks/dashboard.py), which would take an agent process (about 45 MB of
memory) each.

A simulated robot authenticates on /ws/robot/, runs the Skills it is told to (their configs
come from the cloud with skill_config_get), reports statuses and locations the way a Robot
Controller does, answers start/stop/migrate commands, and sends synthetic metrics: robot-wide
cpu, ram, bandwidth and battery, per-component cpu and ram, and offloading decisions.

Run one:   python -m tests.browser.simrobot --master ws://127.0.0.1:8000 --robot r1 --token T --skill s1
Run many:  python -m tests.browser.simrobot --master ws://127.0.0.1:8000 --fleet robots.txt   (lines: id token)
"""

from __future__ import annotations

import argparse
import asyncio
import os
import random
import subprocess
import sys
import time
import zlib
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from bridgeos_agent.link import Link
from bridgeos_agent.protocol import Envelope, Event

ROOT = Path(__file__).resolve().parents[2]
DECISION_METRIC = "offloading.decision"
MIGRATION_S = 0.3
# A Skill Manager decides for each movable component every few rounds of metrics.
DECISION_EVERY = 3
PULL_STEP_S = 1.0  # between a simulated pull's progress reports (the agent's: at most one a second)


class SimulatedRobot:
    """One robot over a real socket: statuses, commands and synthetic metrics."""

    def __init__(
        self, master: str, robot_id: str, token: str, *, skills: Iterable[str] = (), period: float = 1.0, seed: int = 0
    ) -> None:
        self.url = master.rstrip("/") + "/ws/robot/"
        self.robot_id = robot_id
        self.token = token
        self.skill_ids = list(skills)
        self.period = period
        self.random = random.Random(seed or zlib.crc32(robot_id.encode()))
        self.link = Link(self.url)
        # skill -> component -> {"allowed": robot|cloud|either, "active": robot|cloud|"", "status": ...}
        self.components: dict[str, dict[str, dict[str, str]]] = {}
        self.offloading = "auto"
        self.tasks: set[asyncio.Task] = set()
        self.levels = {"cpu": 30.0, "ram": 40.0, "bandwidth": 20.0, "battery": 100.0}
        self.rounds = 0

    async def run(self) -> None:
        """Connect, start the configured skills, then serve commands and send metrics until closed."""
        await self.connect()
        await self.serve()

    async def connect(self) -> None:
        """Open the socket and authenticate."""
        await self.link.connect(Event.AUTHENTICATION_ROBOT, {"robot": self.robot_id, "token": self.token})

    async def serve(self) -> None:
        """Start the configured skills, then serve commands and send metrics until the link closes."""
        try:
            commands = asyncio.create_task(self.serve_commands())
            for skill_id in self.skill_ids:
                answer = await self.link.request(Event.SKILL_CONFIG_GET, {"skill": skill_id})
                if answer.event == Event.SKILL_CONFIG:
                    await self.start_skill(skill_id, answer.data["config"])
            metrics = asyncio.create_task(self.send_metrics())
            closed = asyncio.create_task(self.link.closed.wait())
            await asyncio.wait({commands, metrics, closed}, return_when=asyncio.FIRST_COMPLETED)
            for task in (commands, metrics, closed, *self.tasks):
                task.cancel()
        finally:
            await self.link.close()

    # ------------------------------------------------------------------ commands from the cloud

    async def serve_commands(self) -> None:
        """Apply each command the cloud relays; the link has already acked it, which is the reply."""
        while True:
            envelope = await self.link.next(timeout=None)
            self.spawn(self.apply(envelope))

    def spawn(self, coroutine: Any) -> None:
        task = asyncio.create_task(coroutine)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)

    async def apply(self, envelope: Envelope) -> None:
        data = envelope.data
        event = envelope.event
        if event == Event.ROBOT_CONFIG:
            self.offloading = data["config"].get("offloading", self.offloading)
        elif event == Event.SKILL_START:
            await self.start_skill(data["skill"], data.get("config") or {})
        elif event == Event.SKILL_STOP:
            await self.stop_skill(data["skill"])
        elif event == Event.COMPONENT_START:
            await self.set_component(data["skill"], data["component"], "running", data["location"])
        elif event == Event.COMPONENT_STOP:
            await self.set_component(data["skill"], data["component"], "stopped", None)
        elif event == Event.COMPONENT_MIGRATE:
            await self.migrate(data["skill"], data["component"], data.get("location"))
        elif event == Event.OFFLOADING:
            self.offloading = data["mode"]
            await self.link.send(Event.OFFLOADING, {"mode": self.offloading})

    async def start_skill(self, skill_id: str, config: dict[str, Any]) -> None:
        await self.link.send(Event.SKILL_STATUS, {"skill": skill_id, "status": "starting"})
        components = self.components.setdefault(skill_id, {})
        for component_id, component in config.get("components", {}).items():
            allowed = component.get("location", "robot")
            state = components.setdefault(component_id, {"allowed": allowed, "active": "", "status": "stopped"})
            location = state["active"] or ("cloud" if allowed == "cloud" else "robot")
            image = (component.get("robot") or {}).get("image")
            if image and location == "robot":
                await self.pull(skill_id, component_id, image)
            await self.set_component(skill_id, component_id, "running", location)
            if image and location == "robot":
                container = {"runtime": "docker", "id": f"{component_id}-container", "image": image}
                data = {"skill": skill_id, "component": component_id, "location": "robot", "container": container}
                await self.link.send(Event.COMPONENT_INFORMATION, data)
        await self.link.send(Event.SKILL_STATUS, {"skill": skill_id, "status": "running"})

    async def pull(self, skill_id: str, component_id: str, image: str, total: int = 50_000_000) -> None:
        """Report a pull of a component's image as the agent does: bytes done of its size, a second apart."""
        await self.set_component(skill_id, component_id, "starting", "robot")
        for done in range(0, total + 1, total // 4):
            pull = {"image": image, "done": done, "total": total}
            container = {"runtime": "docker", "image": image, "pull": pull}
            data = {"skill": skill_id, "component": component_id, "location": "robot", "container": container}
            await self.link.send(Event.COMPONENT_INFORMATION, data)
            await asyncio.sleep(PULL_STEP_S)

    async def stop_skill(self, skill_id: str) -> None:
        await self.link.send(Event.SKILL_STATUS, {"skill": skill_id, "status": "stopping"})
        for component_id in self.components.get(skill_id, {}):
            await self.set_component(skill_id, component_id, "stopped", None)
        await self.link.send(Event.SKILL_STATUS, {"skill": skill_id, "status": "stopped"})

    async def set_component(self, skill_id: str, component_id: str, status: str, location: str | None) -> None:
        state = self.components.setdefault(skill_id, {}).setdefault(
            component_id, {"allowed": "either", "active": "", "status": "stopped"}
        )
        state["status"] = status
        data = {"skill": skill_id, "component": component_id, "status": status}
        if location:
            state["active"] = location
            data["location"] = location
        await self.link.send(Event.COMPONENT_STATUS, data)

    async def migrate(self, skill_id: str, component_id: str, target: str | None) -> None:
        """Move a component the way a Skill Manager does: migrating, new location, running there."""
        state = self.components.get(skill_id, {}).get(component_id)
        if state is None:
            return
        source = state["active"] or "robot"
        target = target or ("cloud" if source == "robot" else "robot")
        await self.set_component(skill_id, component_id, "migrating", source)
        await asyncio.sleep(MIGRATION_S)
        state["active"] = target
        await self.link.send(
            Event.COMPONENT_LOCATION, {"skill": skill_id, "component": component_id, "location": target}
        )
        await self.set_component(skill_id, component_id, "running", target)

    # ------------------------------------------------------------------ synthetic metrics

    def walk(self, name: str, low: float, high: float, step: float) -> float:
        value = self.levels[name] + self.random.uniform(-step, step)
        self.levels[name] = min(high, max(low, value))
        return round(self.levels[name], 2)

    def points(self, now: float) -> list[dict[str, Any]]:
        """Return one round of metrics: the robot's, each running component's, and decisions."""
        self.rounds += 1
        battery = self.levels["battery"] = max(5.0, self.levels["battery"] - self.random.uniform(0, 0.05))
        points: list[dict[str, Any]] = [
            {"name": "cpu", "value": self.walk("cpu", 2, 98, 6), "ts": now},
            {"name": "ram", "value": self.walk("ram", 10, 95, 3), "ts": now},
            {"name": "bandwidth", "value": self.walk("bandwidth", 0, 100, 5), "ts": now},
            {"name": "battery", "value": round(battery, 2), "ts": now},
            {"name": "ram_used", "value": round(self.levels["ram"] * 20.48, 1), "ts": now},
            {"name": "net_rx:eth0", "value": round(self.levels["bandwidth"] * 60_000, 1), "ts": now},
            {"name": "net_tx:eth0", "value": round(self.levels["bandwidth"] * 40_000, 1), "ts": now},
        ]
        for skill_id, components in self.components.items():
            for component_id, state in components.items():
                if state["status"] != "running":
                    continue
                share = 0.2 if state["active"] == "cloud" else 1.0
                scope = {"skill": skill_id, "component": component_id, "ts": now}
                points.append({"name": "cpu", "value": round(self.random.uniform(5, 40) * share, 2), **scope})
                points.append({"name": "ram", "value": round(self.random.uniform(60, 300), 1), **scope})
                if state["allowed"] == "either" and self.rounds % DECISION_EVERY == 0:
                    points.append(self.decision(state, scope))
        return points

    def decision(self, state: dict[str, str], scope: dict[str, Any]) -> dict[str, Any]:
        """Invent one decision to stay: both locations' policy costs and the expected reward."""
        here = state["active"] or "robot"
        there = "cloud" if here == "robot" else "robot"
        cost_robot = round(self.random.uniform(0.2, 1.0), 3)
        cost_cloud = round(self.random.uniform(0.2, 1.0), 3)
        costs = {"robot": cost_robot, "cloud": cost_cloud}
        reward = round(costs[here] - costs[there], 3)
        # A real manager logs each move as an offloading_decision event; this robot never moves on its own.
        labels = {
            "decision": "stay",
            "location": here,
            "target": there,
            "cost_robot": str(cost_robot),
            "cost_cloud": str(cost_cloud),
            "policy": "performance",
            "decided_by": "estimate",
        }
        return {"name": DECISION_METRIC, "value": reward, "labels": labels, **scope}

    async def send_metrics(self) -> None:
        loop = asyncio.get_running_loop()
        next_at = loop.time() + self.random.uniform(0, self.period)
        while True:
            await asyncio.sleep(max(0.0, next_at - loop.time()))
            next_at += self.period
            await self.link.send(Event.METRICS, {"metrics": self.points(time.time())})


# --------------------------------------------------------------------------- starting them


def simulator_command(
    master: str, robot_id: str, token: str, *, skills: Iterable[str] = (), period: float = 1.0
) -> list[str]:
    """Return the command line that runs one simulated robot."""
    command = [sys.executable, "-m", "tests.browser.simrobot", "--master", master, "--robot", robot_id]
    command += ["--token", token, "--period", str(period)]
    for skill in skills:
        command += ["--skill", skill]
    return command


def start_simulated_robot(
    master: str, robot_id: str, token: str, *, skills: Iterable[str] = (), period: float = 1.0, log: Path | None = None
) -> subprocess.Popen:
    """Start a simulated robot in its own process, as a real robot's agent would run."""
    out = log.open("ab") if log else subprocess.DEVNULL
    try:
        return subprocess.Popen(
            simulator_command(master, robot_id, token, skills=skills, period=period),
            cwd=ROOT,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    finally:
        if log:
            out.close()


def stop_simulated_robot(process: subprocess.Popen) -> None:
    """Stop a simulated robot's process (its socket closes, and the cloud marks it offline)."""
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


async def run_fleet(robots: list[SimulatedRobot], *, connect_concurrency: int = 25) -> None:
    """Run many simulated robots in one event loop, connecting a few at a time."""
    gate = asyncio.Semaphore(connect_concurrency)

    async def one(robot: SimulatedRobot) -> None:
        try:
            async with gate:
                await robot.connect()
            await robot.serve()
        except Exception as exc:
            print(f"{robot.robot_id}: {exc!r}", file=sys.stderr, flush=True)

    await asyncio.gather(*(one(robot) for robot in robots))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--master", required=True, help="the cloud, e.g. ws://127.0.0.1:8000")
    parser.add_argument("--robot")
    parser.add_argument("--token")
    parser.add_argument("--skill", action="append", default=[], help="a Skill to run from the start (repeatable)")
    parser.add_argument("--fleet", type=Path, help="a file of 'robot_id token' lines: run them all")
    parser.add_argument("--period", type=float, default=1.0, help="seconds between two rounds of metrics")
    args = parser.parse_args()
    if args.fleet:
        pairs = [line.split() for line in args.fleet.read_text().splitlines() if line.strip()]
        robots = [SimulatedRobot(args.master, rid, tok, skills=args.skill, period=args.period) for rid, tok in pairs]
    elif args.robot and args.token:
        robots = [SimulatedRobot(args.master, args.robot, args.token, skills=args.skill, period=args.period)]
    else:
        parser.error("give --robot and --token, or --fleet")
    print(f"simulating {len(robots)} robot(s) against {args.master}", flush=True)
    asyncio.run(run_fleet(robots))


if __name__ == "__main__":
    main()
