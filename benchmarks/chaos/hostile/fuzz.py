"""Attack (a): hostile frames through every WebSocket door, counting what the server failed on."""

from __future__ import annotations

import enum
import json
import random
import time
import typing
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from benchmarks._common import log
from benchmarks.chaos import Outcome
from benchmarks.chaos.hostile.rules import websocket_routes
from benchmarks.chaos.hostile.world import NAME, RUN, SKILL, World, daphne_errors
from benchmarks.chaos.rig import changed, snapshot

# Close codes that mean the server failed rather than refused: internal error, and a socket dropped unclosed.
SERVER_ERROR_CLOSES = {1011, 1006}
BATCH = 50  # fuzzed frames between two sentinels


def filler(annotation: Any, name: str, robot: str) -> Any:
    """Return a value a payload field of this name and type accepts, aimed at ``robot``."""
    known = {
        "robot": robot,
        "robots": [robot],
        "skill": SKILL,
        "component": "sampler",
        "volume": "data",
        "token": "x" * 20,
        "changes": {"threshold": 0.5},
    }
    if name in known:
        return known[name]
    origin = typing.get_origin(annotation)
    args = [a for a in typing.get_args(annotation) if a is not type(None)]
    if origin in (typing.Union, getattr(__import__("types"), "UnionType", None)) and args:
        return filler(args[0], name, robot)
    if origin is typing.Annotated:
        return filler(args[0], name, robot)
    if origin is typing.Literal:
        return args[0]
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        values = [m.value for m in annotation]
        return "cloud" if "cloud" in values else values[0]
    if origin is list or annotation is list:
        return ["cpu"] if name == "names" else []
    if origin is dict or annotation is dict:
        return {}
    if annotation is bool:
        return False
    if annotation is int:
        return 1
    if annotation is float:
        return 1.0
    return "x"


def valid_data(event: str, robot: str) -> dict[str, Any] | None:
    """Build a payload for ``event`` that validates, naming ``robot``; None if the model needs more than fillers."""
    from bridgeos_agent import protocol

    model = protocol.PAYLOADS.get(event)
    if model is None:
        return {}
    data = {
        name: filler(f.annotation, name, robot)
        for name, f in model.model_fields.items()
        if f.is_required() or name == "robot"
    }
    try:
        protocol.make(event, data, now=time.time())
    except protocol.ProtocolError:
        return None
    return data


class FrameFuzzer:
    """Deterministic hostile frames of every kind, never a valid state change (that one may change state)."""

    JUNK: typing.ClassVar[list[Any]] = [
        None,
        True,
        0,
        -1,
        2**70,
        1.5e308,
        "",
        "x" * 300,
        [],
        {},
        [1, [2, [3]]],
        {"a": {"b": None}},
        "\x00",
        "\ud800",
        "../../etc/passwd",
        "' OR 1=1 --",
    ]

    def __init__(self, seed: int, direction: Any, robot: str, replays: list[str]) -> None:
        from bridgeos_agent import protocol

        self.rng = random.Random(seed)
        self.protocol = protocol
        self.direction = direction
        self.robot = robot
        self.replays = replays
        self.events = sorted(protocol.EVENTS)
        self.kinds: Counter[str] = Counter()

    def junk(self) -> Any:
        rng = self.rng
        if rng.random() < 0.3:
            return {
                rng.choice(
                    [
                        "robot",
                        "skill",
                        "component",
                        "metrics",
                        "config",
                        "changes",
                        "location",
                        "status",
                        rng.choice(self.events),
                    ]
                ): self.junk()
                for _ in range(rng.randint(0, 4))
            }
        return rng.choice(self.JUNK)

    def envelope(self) -> dict[str, Any]:
        rng = self.rng
        event = rng.choice(self.events)
        data = valid_data(event, self.robot) or {}
        data = dict(data)
        for _ in range(rng.randint(1, 3)):  # wrong fields: drop one, set one to junk, add one
            choice = rng.random()
            if data and choice < 0.3:
                data.pop(rng.choice(list(data)))
            elif data and choice < 0.7:
                data[rng.choice(list(data))] = self.junk()
            else:
                data[rng.choice(["extra", "robot", "metrics", "skill"])] = self.junk()
        return {"event": event, "id": f"f{rng.randrange(10**9)}", "reply_to": None, "data": data, "ts": time.time()}

    def one(self) -> tuple[str, str | bytes]:
        """Return (kind, frame)."""
        rng = self.rng
        roll = rng.random()
        if self.replays and roll < 0.05:
            frame = json.loads(rng.choice(self.replays))
            # Half the replays carry other data under the applied id: still applied never again.
            if rng.random() < 0.5 and "metrics" in frame["data"]:
                frame["data"]["metrics"] = [{"name": "replayed", "value": rng.random(), "ts": time.time()}]
            if rng.random() < 0.5 and "mode" in frame["data"]:
                frame["data"]["mode"] = rng.choice(["auto", "robot", "cloud"])
            return "replayed_id", json.dumps(frame)
        if roll < 0.15:
            text = json.dumps(self.envelope())
            cut = rng.randrange(1, len(text))
            return "malformed_json", rng.choice(
                [text[:cut], text[:cut] + "}" * rng.randint(0, 3), text.replace(":", ";", 1), text + ","]
            )
        if roll < 0.30:
            return "wrong_types", json.dumps(
                {
                    "event": self.junk(),
                    "id": self.junk(),
                    "reply_to": self.junk(),
                    "data": self.junk(),
                    "ts": self.junk(),
                }
            )
        if roll < 0.31:
            return "deep_nesting", "[" * 100_000 + "]" * 100_000
        if roll < 0.313:
            size = rng.choice([1_500_000, 2_100_000, 3_000_000])
            return "huge", json.dumps(
                {"event": "metrics", "id": "huge", "data": {"metrics": [{"name": "x" * size, "value": 1, "ts": 1}]}}
            )
        if roll < 0.43:
            return "binary_junk", rng.randbytes(rng.randint(1, 400))
        if roll < 0.50:
            return "text_junk", "".join(chr(rng.randint(1, 0x2FFF)) for _ in range(rng.randint(1, 200)))
        return "wrong_fields", json.dumps(self.envelope())

    def frames(self) -> Iterator[tuple[str, str | bytes]]:
        """Yield hostile frames forever, skipping any that would be a valid, state-changing request."""
        protocol = self.protocol
        while True:
            kind, frame = self.one()
            if kind != "replayed_id":
                try:
                    valid = protocol.decode(frame, direction=self.direction)
                    # A valid state change may change state, and a robot's valid error report is logged.
                    if valid.event in protocol.REQUIRES_ACK or valid.event in ("error_message", "authentication_robot"):
                        continue
                    if valid.event == "authentication_client":
                        continue
                except protocol.ProtocolError:
                    pass
            self.kinds[kind] += 1
            yield kind, frame


@dataclass
class Door:
    """How to open, authenticate on and probe one WebSocket door."""

    route: str
    auth: Callable[[], str] | None  # the first frame that authenticates; None: door unknown, fuzz before auth only
    sentinel: Callable[[str], str] | None
    direction: Any = None
    robot: str = "alice-bot"
    # A valid state change applied on the fuzzing socket first, so the fuzzer can replay its id.
    prime: str | None = None
    # The robot door remembers applied ids across connections; the client door only per socket.
    dedup_survives_reconnect: bool = True


@dataclass
class FuzzTally:
    sent: int = 0
    server_errors: int = 0
    closes: Counter = field(default_factory=Counter)
    errors: list[str] = field(default_factory=list)

    def error(self, what: str) -> None:
        self.server_errors += 1
        if len(self.errors) < 5:
            self.errors.append(what[:300])


def open_door(world: World, door: Door) -> Any:
    from websockets.sync.client import connect

    ws = connect(world.ws + "/" + door.route.lstrip("/"), max_size=2**23, open_timeout=10)
    if door.auth is not None:
        ws.send(door.auth())
        first = json.loads(ws.recv(timeout=10))
        if first["event"] != "authentication_success":
            raise RuntimeError(f"{door.route}: could not authenticate: {first}")
    return ws


def drain(ws: Any, sentinel_id: str, tally: FuzzTally, last: str) -> None:
    """Read answers until the sentinel's, acking what needs it and counting internal errors."""
    from bridgeos_agent import protocol

    while True:
        answer = json.loads(ws.recv(timeout=20))
        data = answer.get("data") or {}
        if answer["event"] == "error_message" and (
            data.get("code") == "internal_error" or "Traceback" in str(data.get("message"))
        ):
            tally.error(f"internal error after {last!r}: {answer}")
        if answer["event"] in protocol.REQUIRES_ACK:
            ws.send(protocol.encode(protocol.ack_frame(answer["id"], now=time.time())))
        if answer.get("reply_to") == sentinel_id:
            return


def sentinel_of(door: Door) -> Callable[[str], str]:
    """The door's sentinel request: a door with an authentication recipe has one."""
    if door.sentinel is None:
        raise ValueError(f"/{door.route} has no sentinel")
    return door.sentinel


def fuzz_door(world: World, door: Door, frames: int, seed: int, primed: Callable[[], None]) -> FuzzTally:
    """Send ``frames`` hostile frames through one door, reconnecting after every close the server makes.

    ``primed`` is called once the door's valid state change is applied, before any hostile frame.
    """
    from websockets.exceptions import ConnectionClosed

    tally = FuzzTally()
    replays: list[str] = []
    fuzzer = FrameFuzzer(seed, door.direction, door.robot, replays)
    stream = fuzzer.frames()
    ws = None
    if door.auth is not None:
        ws = open_door(world, door)
        if door.prime is not None:
            ws.send(door.prime)
            # Its answer (a metrics ack comes once the rows are committed), then a sentinel's.
            drain(ws, json.loads(door.prime)["id"], tally, "prime")
            ws.send(sentinel_of(door)("primed"))
            drain(ws, "primed", tally, "prime")
            replays.append(door.prime)
    primed()
    # One in twenty goes first on a fresh socket: before authentication, every door must refuse it.
    before_auth = max(10, frames // 20)
    for _ in range(before_auth):
        kind, frame = next(stream)
        tally.sent += 1
        try:
            fresh = open_door(world, Door(door.route, None, None))
            fresh.send(frame)
            answer = json.loads(fresh.recv(timeout=10))
            if answer["event"] != "authentication_failure":
                tally.error(f"{kind} before authentication answered {answer}")
            fresh.close()
        except ConnectionClosed as exc:
            code = exc.rcvd.code if exc.rcvd else 1006
            tally.closes[f"{code} before auth"] += 1
            if code in SERVER_ERROR_CLOSES and kind != "huge":
                tally.error(f"{kind} before authentication closed with {code}")
    if ws is None:
        return tally
    batch, last, n = 0, "", 0
    while tally.sent < frames:
        kind, frame = next(stream)
        tally.sent += 1
        last = kind
        try:
            ws.send(frame)
            batch += 1
            if batch >= BATCH or kind == "huge" or tally.sent >= frames:
                n += 1
                sentinel = f"sentinel-{n}"
                ws.send(sentinel_of(door)(sentinel))
                drain(ws, sentinel, tally, last)
                batch = 0
        except ConnectionClosed as exc:
            code = exc.rcvd.code if exc.rcvd else 1006
            tally.closes[f"{code} after {kind}"] += 1
            # A frame over daphne's 2 MiB limit is dropped with the connection (autobahn); that is a refusal.
            if code in SERVER_ERROR_CLOSES and not (kind == "huge" and code == 1006):
                tally.error(f"closed with {code} after a {kind} frame")
            ws = open_door(world, door)
            batch = 0
            if not door.dedup_survives_reconnect:
                replays.clear()  # on a new socket the same id is a new request
        except TimeoutError:
            tally.error(f"no answer within 20 s after a {kind} frame")
            ws.close()
            ws = open_door(world, door)
            batch = 0
    ws.close()
    log(f"  {door.route}: {dict(fuzzer.kinds)}; closes {dict(tally.closes)}")
    return tally


def doors(world: World) -> dict[str, Door]:
    """Recipes for the doors this scenario knows; a route without one is fuzzed before authentication only."""
    from bridgeos_agent.protocol import Direction

    robot_token = world.robot_tokens["alice-bot"]
    return {
        "ws/robot/": Door(
            "ws/robot/",
            lambda: json.dumps(
                {"event": "authentication_robot", "id": "auth", "data": {"robot": "alice-bot", "token": robot_token}}
            ),
            lambda sid: json.dumps({"event": "robot_config_get", "id": sid, "data": {}}),
            Direction.ROBOT_TO_CLOUD,
            prime=json.dumps(
                {
                    "event": "metrics",
                    "id": f"primed-metrics-{RUN}",
                    "data": {"metrics": [{"name": "primed", "value": 1.0, "ts": time.time()}]},
                }
            ),
        ),
        "ws/client/": Door(
            "ws/client/",
            lambda: json.dumps(
                {"event": "authentication_client", "id": "auth", "data": {"token": world.tokens["alice"]}}
            ),
            lambda sid: json.dumps({"event": "robot_config_get", "id": sid, "data": {"robot": "alice-bot"}}),
            Direction.CLIENT_TO_CLOUD,
            prime=json.dumps(
                {
                    "event": "offloading",
                    "id": f"primed-offloading-{RUN}",
                    "data": {"robot": "alice-bot", "mode": "manual"},
                }
            ),
            dedup_survives_reconnect=False,
        ),
    }


def fuzz_outcomes(world: World, daphne: Any, frames: int) -> list[Outcome]:
    """Fuzz every WebSocket door the routing lists; one outcome per door."""
    recipes = doors(world)
    outcomes = []
    for i, route in enumerate(websocket_routes()):
        door = recipes.get(route) or Door(route, None, None)
        before: dict[str, str] = {}
        log_before = len(daphne.log_tail(10**9))
        started = time.monotonic()

        def take_before(into: dict[str, str] = before) -> None:
            into.update(snapshot())

        tally = fuzz_door(world, door, frames, seed=7_000 + i, primed=take_before)
        time.sleep(0.5)  # let the last frames' database work finish before comparing
        after = snapshot()
        in_log = daphne_errors(daphne.log_tail(10**9)[log_before:])
        errors = tally.server_errors + in_log
        diff = changed(before, after)
        known = door.auth is not None
        detail = (
            f"{tally.sent} frames in {time.monotonic() - started:.1f} s; closes {dict(tally.closes)}; "
            f"{tally.server_errors} internal errors, {in_log} in daphne's log; tables changed: {diff or 'none'}"
            + ("" if known else "; no recipe for this door: fuzzed before authentication only")
            + (f"; first: {tally.errors}" if tally.errors else "")
        )
        outcomes.append(
            Outcome(
                scenario=NAME,
                injected=f"{tally.sent} fuzzed frames on /{route}",
                sent=tally.sent,
                passed=errors == 0 and not diff and known,
                detail=detail,
                figures={"fuzz_frames": tally.sent, "fuzz_server_errors": errors},
            )
        )
    return outcomes
