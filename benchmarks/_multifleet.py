"""Thousands of simulated robots multiplexed in one process, so what is measured is the cloud, not the fleet.

Every robot is an ``asyncio.Protocol`` on its own TCP connection, speaking WebSocket through
websockets' sans-I/O ``ClientProtocol`` (the library frames and masks; no task or thread per
robot) and the bridgeOS wire protocol as the real agent does: ``authentication_robot`` with its
own token, an ``ack`` for every frame that needs one, a WebSocket ping every heartbeat interval
(the agent's default 5 s), one ``metrics`` frame per sample interval carrying its points. One timer
walks the fleet in slices for heartbeats and metrics, so their cost is spread evenly over time.

``FleetProcess`` runs the fleet in a child process and drives it through a pipe; every answer
carries the child's own CPU time, printed beside the cloud's. The real agent stays the reference
for behaviour: tests/cloud/test_tenk_fleet.py checks the two side by side.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import multiprocessing as mp
import resource
import time
import uuid
from typing import Any
from urllib.parse import urlsplit

NEEDS_ACK = frozenset(
    {
        "connection_established",
        "robot_config",
        "skill_start",
        "skill_stop",
        "skill_add",
        "skill_remove",
        "component_start",
        "component_stop",
        "robot_start",
        "robot_stop",
        "robot_restart",
        "offloading",
        "robot_rekey",
    }
)
TICK_S = 0.05
HEARTBEAT_S = 5.0
METRIC_NAMES = ("cpu", "ram", "disk", "net_rx", "net_tx", "battery", "temp", "gpu", "io_read", "io_write")


def frame_text(event: str, data: dict[str, Any], frame_id: str, reply_to: str | None = None) -> str:
    """Encode one frame as the agent does."""
    return json.dumps(
        {"event": event, "id": frame_id, "reply_to": reply_to, "data": data, "ts": time.time()},
        separators=(",", ":"),
    )


class SimRobot(asyncio.Protocol):
    """One simulated robot: a TCP connection, a sans-I/O WebSocket client and the agent's replies."""

    def __init__(self, fleet: Fleet, index: int, robot_id: str, token: str, url: str) -> None:
        self.fleet, self.index, self.robot_id, self.token, self.url = fleet, index, robot_id, token, url
        self.transport: asyncio.Transport | None = None
        self.ws: Any = None
        self.started = 0.0
        self.tcp_at: float | None = None
        self.upgraded_at: float | None = None
        self.authenticated_at: float | None = None
        self.failure: str | None = None
        self.closed = False
        self.vanished = False
        self.partial: list[bytes] = []
        self.sent: dict[str, float] = {}  # metric frame id -> when sent, until acked

    # ---------------------------------------------------------------- asyncio.Protocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        from websockets.client import ClientProtocol
        from websockets.uri import parse_uri

        self.transport = transport  # type: ignore[assignment]
        self.tcp_at = time.monotonic()
        self.ws = ClientProtocol(parse_uri(self.url), max_size=2**23)
        self.ws.send_request(self.ws.connect())
        self.flush()

    def data_received(self, data: bytes) -> None:
        from websockets.frames import Opcode
        from websockets.http11 import Response

        self.ws.receive_data(data)
        for event in self.ws.events_received():
            if isinstance(event, Response):
                if self.ws.handshake_exc is not None:
                    self.fail(f"handshake refused: {event.status_code}")
                else:
                    self.upgraded_at = time.monotonic()
                    self.send("authentication_robot", {"robot": self.robot_id, "token": self.token})
                continue
            if event.opcode in (Opcode.TEXT, Opcode.CONT):
                self.partial.append(event.data)
                if event.fin:
                    raw, self.partial = b"".join(self.partial), []
                    self.on_frame(json.loads(raw))
        self.flush()

    def connection_lost(self, exc: Exception | None) -> None:
        self.closed = True
        if self.authenticated_at is None and self.failure is None:
            self.note_failure(f"closed before authenticated ({exc or 'by the cloud'})")
        self.fleet.on_closed(self)

    # ---------------------------------------------------------------- the agent's side

    def on_frame(self, frame: dict[str, Any]) -> None:
        event = frame.get("event")
        if event in NEEDS_ACK and frame.get("reply_to") is None:
            self.send("ack", {}, reply_to=frame["id"])
        if event == "ack":
            sent = self.sent.pop(frame.get("reply_to") or "", None)
            if sent is not None:
                self.fleet.acked(time.monotonic() - sent)
        elif event == "authentication_success":
            self.authenticated_at = time.monotonic()
            self.fleet.on_authenticated(self)
        elif event == "authentication_failure":
            self.fail(f"refused: {frame.get('data', {}).get('reason')}")
        elif event == "error_message":
            self.fleet.errors += 1
            if self.fleet.errors <= 3:
                print(f"{self.robot_id}: error_message {frame.get('data')}", flush=True)
        if event not in ("ack", "authentication_success", "connection_established", "robot_config"):
            self.fleet.commands[event] = self.fleet.commands.get(event, 0) + 1

    def send(self, event: str, data: dict[str, Any], reply_to: str | None = None) -> str:
        frame_id = uuid.uuid4().hex
        self.send_text(frame_text(event, data, frame_id, reply_to))
        return frame_id

    def send_text(self, text: str) -> None:
        if self.ws is None or self.closed or self.vanished:
            return
        self.ws.send_text(text.encode())
        self.flush()

    def send_metrics(self, points: int) -> None:
        if self.authenticated_at is None or self.closed or self.vanished:
            return
        now = time.time()
        body = ",".join(
            f'{{"name":"{METRIC_NAMES[i % len(METRIC_NAMES)]}","value":{(self.index + i) % 100}.5,"ts":{now!r}}}'
            for i in range(points)
        )
        frame_id = uuid.uuid4().hex
        self.sent[frame_id] = time.monotonic()
        self.fleet.points_sent += points
        self.send_text(f'{{"event":"metrics","id":"{frame_id}","data":{{"metrics":[{body}]}},"ts":{now!r}}}')

    def ping(self) -> None:
        if self.authenticated_at is not None and not self.closed and not self.vanished:
            self.ws.send_ping(b"")
            self.flush()

    def vanish(self) -> None:
        """Stop answering and reading, as a robot whose network went away without a goodbye."""
        self.vanished = True
        if self.transport is not None:
            self.transport.pause_reading()

    def fail(self, why: str) -> None:
        self.note_failure(why)
        if self.transport is not None:
            self.transport.abort()

    def note_failure(self, why: str) -> None:
        """Keep the first reason this robot failed, and count it once in its fleet."""
        if self.failure is None:
            self.failure = why
            self.fleet.failed += 1

    def flush(self) -> None:
        if self.transport is None or self.transport.is_closing():
            return
        for chunk in self.ws.data_to_send():
            if chunk:
                self.transport.write(chunk)


class Fleet:
    """The simulated robots of one process and the timer that heartbeats them and sends their metrics."""

    def __init__(self, robots: list[tuple[str, str]], urls: list[str], heartbeat_s: float) -> None:
        self.robots = [
            SimRobot(self, index, robot_id, token, urls[index % len(urls)] + "/ws/robot/")
            for index, (robot_id, token) in enumerate(robots)
        ]
        self.heartbeat_s = heartbeat_s
        self.authenticated = 0
        self.failed = 0  # robots with a failure: counted, as walking 10,000 robots per login cost seconds
        self.closed_after_auth = 0
        self.all_in = asyncio.Event()
        self.errors = 0
        self.commands: dict[str, int] = {}
        self.points_sent = 0
        self.latencies: list[float] = []
        self.acked_at: list[float] = []  # when each of latencies was acked
        self.metrics_every_s = 0.0  # 0: no metrics
        self.points_per_frame = 0
        self.ticker: asyncio.Task | None = None

    def on_authenticated(self, robot: SimRobot) -> None:
        self.authenticated += 1
        if self.authenticated + self.failed >= len(self.robots):
            self.all_in.set()

    def on_closed(self, robot: SimRobot) -> None:
        if robot.authenticated_at is not None:
            self.closed_after_auth += 1
        elif self.authenticated + self.failed >= len(self.robots):
            self.all_in.set()

    def acked(self, seconds: float) -> None:
        self.latencies.append(seconds)
        self.acked_at.append(time.monotonic())

    async def connect(self, within_s: float) -> dict[str, Any]:
        """Open every robot's connection at once; return how long until all authenticated, and who failed."""
        loop = asyncio.get_running_loop()
        began = time.monotonic()

        async def open_one(robot: SimRobot) -> None:
            parts = urlsplit(robot.url)
            robot.started = time.monotonic()
            try:
                await loop.create_connection(lambda: robot, parts.hostname, parts.port)
            except OSError as exc:
                robot.fail(f"connect failed: {exc}")
                robot.closed = True
                self.on_closed(robot)

        await asyncio.gather(*(open_one(robot) for robot in self.robots))
        try:
            await asyncio.wait_for(self.all_in.wait(), within_s)
        except TimeoutError:
            pass
        took = [robot.authenticated_at - began for robot in self.robots if robot.authenticated_at is not None]
        failures: dict[str, int] = {}
        for robot in self.robots:
            if robot.authenticated_at is None:
                why = robot.failure or "no answer"
                failures[why[:80]] = failures.get(why[:80], 0) + 1
        self.ticker = asyncio.ensure_future(self.tick_forever())
        return {
            "stages": {
                stage: spread([getattr(robot, f"{stage}_at") for robot in self.robots], began)
                for stage in ("tcp", "upgraded", "authenticated")
            },
            "connected": len(took),
            "rejected": len(self.robots) - len(took),
            "connect_s": max(took) if len(took) == len(self.robots) else None,
            "p50_s": sorted(took)[len(took) // 2] if took else None,
            "failures": failures,
        }

    async def tick_forever(self) -> None:
        """Walk the fleet in slices: each robot pings every heartbeat and sends metrics every interval."""
        ticks_per_beat = max(1, round(self.heartbeat_s / TICK_S))
        # Ticks keep to the clock, not to a sleep after each: a late tick is caught up, so the rates offered hold.
        first = time.monotonic()
        for tick in itertools.count():
            beat_slot = tick % ticks_per_beat
            for robot in self.robots[beat_slot::ticks_per_beat]:
                robot.ping()
            if self.metrics_every_s > 0:
                ticks_per_metric = max(1, round(self.metrics_every_s / TICK_S))
                metric_slot = tick % ticks_per_metric
                for robot in self.robots[metric_slot::ticks_per_metric]:
                    robot.send_metrics(self.points_per_frame)
            await asyncio.sleep(max(0.0, first + (tick + 1) * TICK_S - time.monotonic()))

    async def drained(self, within_s: float) -> int:
        """Wait until every metric frame sent is acked, at most ``within_s``; return how many are not."""
        for _ in range(max(1, round(within_s / TICK_S))):
            unacked = sum(len(robot.sent) for robot in self.robots)
            if not unacked:
                return 0
            await asyncio.sleep(TICK_S)
        return sum(len(robot.sent) for robot in self.robots)

    def vanish(self, how_many: int) -> list[str]:
        """Make the last ``how_many`` connected robots vanish without a goodbye; return their ids."""
        chosen = [robot for robot in self.robots if robot.authenticated_at is not None and not robot.closed]
        chosen = chosen[-how_many:]
        for robot in chosen:
            robot.vanish()
        return [robot.robot_id for robot in chosen]

    def close(self) -> None:
        if self.ticker is not None:
            self.ticker.cancel()
        for robot in self.robots:
            if robot.transport is not None:
                robot.transport.abort()


def spread(moments: list[float | None], began: float) -> dict[str, float | None]:
    """Return the median and last of moments since ``began``, in seconds (where a storm's time goes)."""
    took = sorted(moment - began for moment in moments if moment is not None)
    if not took:
        return {"p50_s": None, "last_s": None}
    return {"p50_s": round(took[len(took) // 2], 2), "last_s": round(took[-1], 2)}


def cpu_s() -> float:
    """Return this process's CPU time (user + system) so far."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def serve(conn: Any, robots: list[tuple[str, str]], urls: list[str], heartbeat_s: float) -> None:
    """Run a fleet in this (child) process, doing what the parent asks over ``conn``."""
    import gc

    gc.freeze()  # the fleet's objects live as long as the process: keep the collector off them

    async def run() -> None:
        loop = asyncio.get_running_loop()
        fleet = Fleet(robots, urls, heartbeat_s)
        while True:
            command, args = await loop.run_in_executor(None, conn.recv)
            cpu_before, wall_before = cpu_s(), time.monotonic()
            answer: dict[str, Any] = {}
            if command == "connect":
                answer = await fleet.connect(**args)
            elif command == "idle":
                await asyncio.sleep(args["seconds"])
            elif command == "ingest":
                fleet.latencies, fleet.acked_at, fleet.points_sent = [], [], 0
                began = time.monotonic()
                fleet.points_per_frame, fleet.metrics_every_s = args["points_per_frame"], args["every_s"]
                await asyncio.sleep(args["seconds"])
                fleet.metrics_every_s = 0.0
                unacked = await fleet.drained(args.get("drain_s", 2.0))
                answer = {
                    "points_sent": fleet.points_sent,
                    "latencies": fleet.latencies,
                    "acked_after_s": [moment - began for moment in fleet.acked_at],
                    "unacked_frames": unacked,
                }
            elif command == "vanish":
                answer = {"robots": fleet.vanish(args["robots"])}
            elif command == "state":
                answer = {
                    "connected": sum(1 for r in fleet.robots if r.authenticated_at and not r.closed),
                    "closed_after_auth": fleet.closed_after_auth,
                    "errors": fleet.errors,
                    "commands": dict(fleet.commands),
                }
            elif command == "stop":
                fleet.close()
                conn.send({"cpu_s": cpu_s()})
                return
            answer["cpu_s"] = cpu_s() - cpu_before
            answer["wall_s"] = time.monotonic() - wall_before
            conn.send(answer)

    asyncio.run(run())


class FleetProcess:
    """A simulated fleet in a child process of its own, driven from the parent."""

    def __init__(self, robots: list[tuple[str, str]], urls: list[str], heartbeat_s: float = HEARTBEAT_S) -> None:
        context = mp.get_context("spawn")
        self.conn, child = context.Pipe()
        self.process = context.Process(target=serve, args=(child, robots, urls, heartbeat_s), daemon=True)
        self.process.start()

    def ask(self, command: str, timeout: float = 600.0, **args: Any) -> dict[str, Any]:
        self.conn.send((command, args))
        if not self.conn.poll(timeout):
            raise TimeoutError(f"the simulated fleet did not answer {command} within {timeout} s")
        return self.conn.recv()

    def cpu_pct(self, answer: dict[str, Any]) -> float:
        """Return the fleet's CPU over one answer's span, in percent of a core."""
        return round(100 * answer["cpu_s"] / max(answer["wall_s"], 1e-6), 1)

    def stop(self) -> None:
        if self.process.is_alive():
            try:
                self.ask("stop", timeout=30)
            except (TimeoutError, OSError, EOFError):
                pass
            self.process.join(10)
        if self.process.is_alive():
            self.process.kill()
