"""Scenario 7, hostile input: fuzzed frames on every door, schemathesis on every API route, cross-tenant access.

Against a real daphne: (a) thousands of fuzzed frames per WebSocket door (malformed JSON, wrong types,
huge frames, binary junk, valid-looking envelopes with wrong fields, frames before authentication,
replayed ids), counting server errors (`internal_error` answers, closes with 1011, tracebacks in
daphne's log) and proving no table changed; (b) schemathesis over every operation of the published
OpenAPI schema, 0 server errors and no change from a refused request; (c) a robot token acting as
another robot and a user reaching another user's robot through every door the URL resolver and the
WebSocket routing list, all refused.
"""

from __future__ import annotations

import contextlib
import enum
import io
import json
import logging
import random
import re
import threading
import time
import typing
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

from benchmarks._common import log
from benchmarks.chaos import Outcome
from benchmarks.chaos.rig import changed, snapshot, start_daphne
from benchmarks.chaos.rig import shared_cloud_env as cloud_env

NAME = "hostile"
INJECTS = "hostile input: fuzzed frames on every WebSocket door, schemathesis on every API route, cross-tenant access"

SKILL = "people-detection"
# Lifted so the fuzzer reaches the handlers, not the rate and brute-force limits in front of them.
LIMITS_OFF = {
    "BRIDGEOS_ROBOT_FRAMES_PER_S": "1000000",
    "BRIDGEOS_ROBOT_FRAME_BURST": "1000000",
    "BRIDGEOS_CLIENT_FRAMES_PER_S": "1000000",
    "BRIDGEOS_CLIENT_FRAME_BURST": "1000000",
    "BRIDGEOS_AUTH_FAILURES": "100000000",
    "BRIDGEOS_AUTH_FAILURES_PER_ADDRESS": "100000000",
}
# Close codes that mean the server failed rather than refused: internal error, and a socket dropped unclosed.
SERVER_ERROR_CLOSES = {1011, 1006}
REFUSED = {401, 403, 404}
BATCH = 50  # fuzzed frames between two sentinels
# The cloud remembers a robot's applied frame ids across connections (and runs): valid frames carry this tag.
RUN = f"{random.getrandbits(40):010x}"


# --------------------------------------------------------------------------- the world


@dataclass
class World:
    """Alice owns alice-bot, Bob bob-bot, Carol carol-bot (each with the sample Skill); ops is staff."""

    http: str
    ws: str
    tokens: dict[str, str]  # alice, bob, ops, carol -> API token
    robot_tokens: dict[str, str]  # robot id -> robot token
    sessions: dict[str, str]  # alice, bob -> session key
    template_id: int
    copy_tokens: dict[str, str]  # robot id -> launch token of its cloud copy of the sampler
    recording_id: str  # a finished recording of alice-bot's


def make_world(http: str, ws: str) -> World:
    """Create the users, robots, cloud copies and sessions the scenario plays with."""
    import importlib
    from datetime import timedelta

    from django.conf import settings
    from django.contrib.auth import BACKEND_SESSION_KEY, HASH_SESSION_KEY, SESSION_KEY, get_user_model
    from django.db import connection
    from django.utils import timezone

    from bridgeos_agent.skillconfig import load_sample_skill_config
    from monitoring.models import Metric
    from robots.models import Robot
    from robots.services import create_robot, issue_api_token
    from skills.models import CloudInstance, Component
    from skills.services import add_skill, create_template

    Robot.objects.filter(id__in=["alice-bot", "bob-bot", "carol-bot"]).delete()
    users, tokens, robot_tokens, sessions, copy_tokens = {}, {}, {}, {}, {}
    for name in ("alice", "bob", "ops", "carol"):
        get_user_model().objects.filter(username=f"hostile-{name}").delete()
        users[name] = get_user_model().objects.create_user(f"hostile-{name}", is_staff=name == "ops")
        tokens[name] = issue_api_token(users[name])[0]
    config = load_sample_skill_config().model_dump(mode="json")
    for owner in ("alice", "bob", "carol"):
        robot, robot_tokens[f"{owner}-bot"] = create_robot(f"{owner}-bot", users[owner])
        add_skill(robot, config)
    store = importlib.import_module(settings.SESSION_ENGINE).SessionStore
    for name in ("alice", "bob"):
        session = store()
        session[SESSION_KEY] = str(users[name].pk)
        session[BACKEND_SESSION_KEY] = "django.contrib.auth.backends.ModelBackend"
        session[HASH_SESSION_KEY] = users[name].get_session_auth_hash()
        session.create()
        sessions[name] = session.session_key
    for robot_id in ("alice-bot", "bob-bot"):
        component = Component.objects.get(skill__robot_id=robot_id, skill__skill_id=SKILL, component_id="sampler")
        copy_tokens[robot_id] = f"copy{robot_id.replace('-', '')}{random.randrange(10**9)}"
        CloudInstance.objects.update_or_create(
            component=component, defaults={"desired": CloudInstance.Desired.RUNNING, "token": copy_tokens[robot_id]}
        )
    a_minute_ago = timezone.now() - timedelta(minutes=1)
    Metric.objects.bulk_create(
        Metric(robot_id=robot_id, name="cpu", value=0.5, ts=a_minute_ago) for robot_id in ("alice-bot", "bob-bot")
    )
    template_config = {**config, "skill_id": "hostile-counting", "skill": "Hostile counting"}
    from skills.models import SkillTemplate

    SkillTemplate.objects.filter(name="Hostile counting").delete()
    template = create_template(name="Hostile counting", config=template_config)
    from recordings.choices import RecordingStatus
    from recordings.models import Recording

    recording = Recording.objects.create(
        robot_id="alice-bot", topics=["/chatter"], status=RecordingStatus.FINISHED, max_bytes=1, max_duration_s=1
    )
    connection.close()
    return World(http, ws, tokens, robot_tokens, sessions, template.pk, copy_tokens, recording.id.hex)


def daphne_errors(log_text: str) -> int:
    """Count what daphne's log says went wrong on the server: tracebacks and 5xx answers."""
    tracebacks = log_text.count("Traceback (most recent call last)")
    answers_5xx = len(re.findall(r'" 5\d\d ', log_text))
    return tracebacks + answers_5xx


# --------------------------------------------------------------------------- a robot socket that records


class RecordingRobot:
    """A robot on /ws/robot/ that acks what needs it and records every other frame the cloud sends it."""

    def __init__(self, ws_url: str, robot_id: str, token: str) -> None:
        from websockets.sync.client import connect

        from bridgeos_agent import protocol

        self.protocol = protocol
        self.ws = connect(ws_url + "/ws/robot/", max_size=2**22)
        self.ws.send(
            json.dumps({"event": "authentication_robot", "id": "auth", "data": {"robot": robot_id, "token": token}})
        )
        first = json.loads(self.ws.recv(timeout=10))
        if first["event"] != "authentication_success":
            raise RuntimeError(f"{robot_id} could not authenticate: {first}")
        self.frames: list[dict] = []
        self.lock = threading.Lock()
        self.reader = threading.Thread(target=self.read, daemon=True)
        self.reader.start()

    def read(self) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            for raw in self.ws:
                frame = json.loads(raw)
                if frame["event"] in self.protocol.REQUIRES_ACK:
                    self.ws.send(self.protocol.encode(self.protocol.ack_frame(frame["id"], now=time.time())))
                with self.lock:
                    self.frames.append(frame)
        except ConnectionClosed:
            pass

    def commands_since(self, index: int) -> list[dict]:
        """Return the frames received since ``index`` that carry an order or a request to the robot."""
        with self.lock:
            got = self.frames[index:]
        # On connecting the cloud sends the robot its own config and connection; nothing else comes unasked.
        return [f for f in got if f["event"] not in ("connection_established", "robot_config", "ack")]

    def count(self) -> int:
        with self.lock:
            return len(self.frames)

    def close(self) -> None:
        self.ws.close()
        self.reader.join(timeout=5)


# --------------------------------------------------------------------------- (a) fuzzed frames


def filler(annotation: Any, name: str, robot: str) -> Any:
    """Return a value a payload field of this name and type accepts, aimed at ``robot``."""
    known = {
        "robot": robot,
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


def websocket_routes() -> list[str]:
    """Every WebSocket route of the cloud's own protocol (event, id and data frames), read from its routing."""
    from bridgeos_cloud.routing import websocket_urlpatterns

    return [str(p.pattern) for p in websocket_urlpatterns if "robot_id" not in str(p.pattern)]


def bridge_routes() -> list[str]:
    """The rosbridge and Foxglove doors of a robot: authorised at the handshake, their frames the robot's to read.

    Their bad input and floods are tested against a real agent (tests/cloud/test_bridge_relay.py);
    here every intruder's handshake on Alice's robot must be refused.
    """
    from bridgeos_cloud.routing import websocket_urlpatterns

    return [str(p.pattern) for p in websocket_urlpatterns if "robot_id" in str(p.pattern)]


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


# --------------------------------------------------------------------------- (b) schemathesis


def schemathesis_outcome(world: World, daphne: Any, examples: int) -> Outcome:
    """Fuzz every operation of the served OpenAPI schema: no 5xx, and nothing written by a refused request."""
    import schemathesis
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st
    from schemathesis import GenerationMode

    schema = schemathesis.openapi.from_url(world.http + "/api/schema/?format=json")
    operations = sorted((method.upper(), path) for path, ops in schema.raw_schema["paths"].items() for method in ops)
    real_ids = {"robot_id": "carol-bot", "skill_id": SKILL, "component_id": "sampler", "template_id": world.template_id}
    calls, server_errors, wrote_when_refused = 0, 0, 0
    failures: list[str] = []
    log_before = len(daphne.log_tail(10**9))
    started = time.monotonic()
    state = [snapshot()]
    for method, path in operations:
        operation = schema[path][method]
        token = world.tokens["ops"] if path.startswith("/api/templates") else world.tokens["carol"]
        cases = st.one_of(
            operation.as_strategy(GenerationMode.POSITIVE), operation.as_strategy(GenerationMode.NEGATIVE)
        )

        @given(case=cases, aim=st.booleans(), method=st.just(method), token=st.just(token))
        @settings(
            max_examples=examples,
            deadline=None,
            derandomize=True,
            database=None,
            suppress_health_check=list(HealthCheck),
        )
        def one(case: Any, aim: bool, method: str, token: str) -> None:
            nonlocal calls, server_errors, wrote_when_refused
            if aim:
                for name, value in real_ids.items():
                    if name in (case.path_parameters or {}):
                        case.path_parameters[name] = value
            response = case.call(base_url=world.http, headers={"Authorization": f"Token {token}"}, timeout=15)
            calls += 1
            status = response.status_code
            if status >= 500:
                server_errors += 1
                if len(failures) < 5:
                    failures.append(f"{method} {case.formatted_path}: {status} {response.text[:200]}")
            # Even a GET may write (GET /api/auth/renew renews), so every request is followed by a
            # snapshot, which is also the state before the next request.
            after = snapshot()
            diff = changed(state[0], after)
            state[0] = after
            if 400 <= status < 500 and diff:
                wrote_when_refused += 1
                if len(failures) < 5:
                    failures.append(f"{method} {case.formatted_path} refused with {status} but wrote {diff}")

        one()
    in_log = daphne_errors(daphne.log_tail(10**9)[log_before:])
    errors = server_errors + in_log
    return Outcome(
        scenario=NAME,
        injected=f"schemathesis over {len(operations)} API operations",
        sent=calls,
        passed=errors == 0 and wrote_when_refused == 0 and len(operations) > 0,
        detail=(
            f"{calls} requests in {time.monotonic() - started:.1f} s; {server_errors} 5xx, "
            f"{in_log} errors in daphne's log; "
            f"{wrote_when_refused} refused requests that wrote" + (f"; first: {failures}" if failures else "")
        ),
        figures={"fuzz_server_errors": errors},
    )


# --------------------------------------------------------------------------- (c) cross-tenant


def http_routes() -> list[tuple[str, Any]]:
    """Every URL pattern the cloud serves (but the admin's own pages), as (route, callback)."""
    from django.urls import URLPattern, URLResolver, get_resolver

    def walk(patterns: list, prefix: str) -> Iterator[tuple[str, Any]]:
        for pattern in patterns:
            if isinstance(pattern, URLResolver):
                yield from walk(pattern.url_patterns, prefix + str(pattern.pattern))
            elif isinstance(pattern, URLPattern):
                yield prefix + str(pattern.pattern), pattern.callback

    return [
        (route, callback) for route, callback in walk(get_resolver().url_patterns, "") if not route.startswith("admin/")
    ]


def methods_of(callback: Any) -> list[str]:
    """The HTTP methods a view answers (GET and POST for a plain function view)."""
    view = getattr(callback, "cls", None) or getattr(callback, "view_class", None)
    if view is None:
        return ["GET", "POST"]
    return [m.upper() for m in ("get", "post", "put", "patch", "delete") if hasattr(view, m)]


# Routes that take no robot: what each gives and why no robot of another user can be reached there.
NO_ROBOT = {
    "": "the fleet page: lists only the user's robots (checked below)",
    "skills/": "the catalog of Skill templates, shared by design",
    "events/": "the event log page: filled by /api/events (checked below)",
    "validate/skill-config": "validates a posted config, touches no robot",
    "validate/robot-config": "validates a posted config, touches no robot",
    "accounts/login/": "login form",
    "accounts/logout/": "logout",
    "api/health": "liveness, no robot data",
    "metrics": "operator scrape, limited to BRIDGEOS_METRICS_ALLOW/TOKEN, not a per-user door",
    "api/auth": "exchanges a password for a token",
    "api/auth/renew": "renews the caller's own token",
    "api/registry/token": "grants repositories of the caller's own namespace only (tests/registry prove it)",
    "api/templates": "catalog, shared by design; writes are staff only",
    "api/templates/<int:template_id>": "catalog, shared by design; writes are staff only",
    "api/schema/": "the OpenAPI schema",
    "api/docs/": "the API docs page",
}
# Routes that take robots in the body or query string, or act on every robot the caller may see.
ROBOTS_IN_BODY = {
    "api/robot",
    "api/robot/start",
    "api/robot/stop",
    "api/robot/shutdown",
    "api/database/query",
    "api/events",
}


@dataclass
class Tenancy:
    attempts: int = 0
    allowed: int = 0
    holes: list[str] = field(default_factory=list)
    doors: Counter = field(default_factory=Counter)
    routes: set[str] = field(default_factory=set)  # robot routes tried, spelled as in the OpenAPI schema

    def judge(self, door: str, what: str, allowed: bool, detail: str = "") -> None:
        self.attempts += 1
        self.doors[door] += 1
        if allowed:
            self.allowed += 1
            self.holes.append(f"{what}: {detail}"[:300])


def published_robot_routes() -> set[str]:
    """The paths of the OpenAPI schema that name a robot: the resolver's enumeration must reach each."""
    from drf_spectacular.generators import SchemaGenerator

    with contextlib.redirect_stderr(io.StringIO()):  # drf-spectacular's naming warnings, printed elsewhere too
        paths = SchemaGenerator().get_schema(request=None, public=True)["paths"]
    return {path for path in paths if "{robot_id}" in path}


def fill_route(route: str, world: World, robot: str, copy_token: str) -> str:
    values = {
        "robot_id": robot,
        "skill_id": SKILL,
        "component_id": "sampler",
        "template_id": str(world.template_id),
        "token": copy_token,
        "path": "status",
        "recording_id": world.recording_id,
    }
    return "/" + re.sub(r"<(?:\w+:)?(\w+)>", lambda m: values[m.group(1)], route)


def bridge_handshakes(world: World, route: str, tally: Tenancy, callers: dict[str, dict[str, str]]) -> None:
    """Open a bridge door of alice-bot as each caller (and with a forged ticket): each must be refused."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    url = world.ws + "/" + re.sub(r"<(?:\w+:)?robot_id>", "alice-bot", route)
    tries = [(who, url, headers) for who, headers in callers.items()]
    tries.append(("a forged ticket", url + "?ticket=" + "f" * 43, {}))
    for who, address, headers in tries:
        try:
            with connect(
                address, additional_headers=headers, subprotocols=["foxglove.websocket.v1"], open_timeout=10
            ) as websocket:
                allowed, detail = True, f"opened ({websocket.subprotocol})"
        except InvalidStatus as exc:
            allowed, detail = exc.response.status_code not in REFUSED, f"{exc.response.status_code}"
        tally.judge("bridge", f"WS /{route} of alice-bot as {who}", allowed, detail)


def destructive_rank(call: tuple[str, str]) -> int:
    """Order robot calls so what would remove a skill, cut alice-bot's link or delete it comes last, in that order."""
    route, method = call
    if method == "DELETE":
        return 3
    if route.endswith(("/token", "/shutdown")):
        return 2
    return 1 if route.endswith("/remove") else 0


def cross_tenant(world: World, alice_robot: RecordingRobot, intruder: str = "bob") -> tuple[Tenancy, list[str]]:
    """Try every door as Bob (and as bob-bot) on alice-bot; return the tally and the routes left unclassified.

    ``intruder`` names whose API token plays Bob on the user doors: the tests hand it staff's, who
    may see every robot, to prove the tally counts an access that is granted.
    """
    import httpx

    tally = Tenancy()
    unclassified: list[str] = []
    bob_api = {"Authorization": f"Token {world.tokens[intruder]}"}
    bob_robot = {"Authorization": f"Token {world.robot_tokens['bob-bot']}"}
    with httpx.Client(base_url=world.http, timeout=15) as http:
        session = httpx.Client(base_url=world.http, timeout=15, cookies={"sessionid": world.sessions["bob"]})

        def attempt(
            door: str,
            method: str,
            url: str,
            headers: dict | None = None,
            client: Any = None,
            refused: frozenset = frozenset(),
            **kw: Any,
        ) -> httpx.Response:
            seen = alice_robot.count()
            response = (client or http).request(method, url, headers=headers or {}, **kw)
            reached = alice_robot.commands_since(seen)
            leaked = response.status_code < 300 and "alice-bot" in response.text
            allowed = bool(reached) or leaked or response.status_code not in REFUSED | {405} | refused
            if door in ("robots-in-body", "page") and response.status_code in (200, 302) and not leaked and not reached:
                allowed = False  # answered, but with nothing of Alice's
            if response.status_code != 405:
                tally.judge(
                    door,
                    f"{method} {url} as {'bob-bot' if headers is bob_robot else 'bob'}",
                    allowed,
                    f"{response.status_code} {response.text[:120]} reached={reached[:1]}",
                )
            return response

        robot_calls = [
            (route, method)
            for route, callback in http_routes()
            if "robot_id" in route
            for method in methods_of(callback)
        ]
        # What would destroy alice-bot or cut its link, were it let through, goes last: it would spoil the rest.
        robot_calls.sort(key=destructive_rank)
        for route, method in robot_calls:
            tally.routes.add("/" + re.sub(r"<(?:\w+:)?(\w+)>", r"{\1}", route))
            url = fill_route(route, world, "alice-bot", "")
            if route.startswith("api/"):
                body = {"location": "cloud", "skill": SKILL, "template": world.template_id, "name": "taken"}
                attempt("rest", method, url, bob_api, json=body)
                attempt("rest", method, url, bob_robot, json=body)
            else:
                attempt("page", method, url, client=session)
        for route in bridge_routes():
            bridge_handshakes(world, route, tally, {"bob": bob_api, "bob-bot": bob_robot, "nobody": {}})
        for route, callback in http_routes():
            if "robot_id" in route:
                continue
            elif "<str:token>" in route:
                for method in methods_of(callback):
                    for token in (world.copy_tokens["bob-bot"], world.tokens["bob"], world.robot_tokens["bob-bot"]):
                        for path in ("components", "metrics/cpu", "../alice-bot/components", "components/alice-bot"):
                            url = fill_route(route, world, "alice-bot", token).replace("/status", "/" + path, 1)
                            # Bob's own copy's token relays to bob-bot, offline here (503); never to alice-bot.
                            attempt(
                                "components-api",
                                method,
                                url + "?robot=alice-bot",
                                refused=frozenset({400, 503}),
                                json={"robot": "alice-bot"},
                            )
            elif route in ROBOTS_IN_BODY:
                for method in methods_of(callback):
                    if route == "api/database/query":
                        for kind in ("metrics", "events"):
                            # A 400 "No robot 'alice-bot'" is what a missing robot gets too.
                            attempt(
                                "robots-in-body",
                                method,
                                "/" + route,
                                bob_api,
                                refused=frozenset({400}),
                                json={"kind": kind, "robots": ["alice-bot"]},
                            )
                    elif route == "api/robot" and method == "POST":
                        # Taking over an existing id: robot ids are one namespace, so this is a 400, never a takeover.
                        attempt(
                            "rest", method, "/" + route, bob_api, refused=frozenset({400}), json={"id": "alice-bot"}
                        )
                    else:
                        attempt("robots-in-body", method, "/" + route + "?robot=alice-bot", bob_api)
            elif route in NO_ROBOT:
                if route in ("", "events/"):
                    attempt("page", "GET", "/" + route, client=session)
            else:
                unclassified.append(route)
        session.close()
    websocket_client_attempts(world, tally, alice_robot)
    websocket_robot_attempts(world, tally)
    return tally, unclassified


def websocket_client_attempts(world: World, tally: Tenancy, alice_robot: RecordingRobot) -> None:
    """As Bob on /ws/client/: every request naming alice-bot is refused, and nothing of alice-bot streams to him."""
    from websockets.sync.client import connect

    from bridgeos_agent import protocol
    from bridgeos_agent.protocol import Direction

    with connect(world.ws + "/ws/client/", max_size=2**22) as ws:
        ws.send(json.dumps({"event": "authentication_client", "id": "auth", "data": {"token": world.tokens["bob"]}}))
        assert json.loads(ws.recv(timeout=10))["event"] == "authentication_success"
        for event in sorted(protocol.EVENTS):
            if (
                not protocol.is_allowed(event, Direction.CLIENT_TO_CLOUD)
                or event in ("ack", "error_message")
                or event.startswith("authentication_")
            ):
                continue
            data = valid_data(event, "alice-bot")
            if data is None:
                tally.judge(
                    "ws-client", f"{event} (could not build a valid request)", True, "the payload filler needs teaching"
                )
                continue
            seen = alice_robot.count()
            ws.send(json.dumps({"event": event, "id": f"x-{event}", "data": data}))
            while True:
                answer = json.loads(ws.recv(timeout=10))
                if answer["event"] in protocol.REQUIRES_ACK:
                    ws.send(protocol.encode(protocol.ack_frame(answer["id"], now=time.time())))
                if answer.get("reply_to") == f"x-{event}" or "alice-bot" in json.dumps(answer):
                    break
            refused = answer["event"] == "error_message" and answer["data"].get("code") in ("not_found", "forbidden")
            tally.judge(
                "ws-client",
                f"{event} for alice-bot as bob",
                not refused or bool(alice_robot.commands_since(seen)),
                json.dumps(answer)[:200],
            )


class Listener:
    """A client on /ws/client/ that keeps every frame its live feed brings, read on a thread of its own."""

    def __init__(self, ws_url: str, token: str) -> None:
        from websockets.sync.client import connect

        self.ws = connect(ws_url + "/ws/client/", max_size=2**22)
        self.ws.send(json.dumps({"event": "authentication_client", "id": "auth", "data": {"token": token}}))
        answer = json.loads(self.ws.recv(timeout=10))
        if answer["event"] != "authentication_success":
            raise RuntimeError(f"the client could not authenticate: {answer}")
        self.frames: list[str] = []
        self.reader = threading.Thread(target=self.read, daemon=True)
        self.reader.start()

    def read(self) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            for raw in self.ws:
                self.frames.append(raw if isinstance(raw, str) else raw.decode(errors="replace"))
        except ConnectionClosed:
            pass

    def close(self) -> None:
        self.ws.close()
        self.reader.join(timeout=5)


def live_feed_attempt(world: World, tally: Tenancy, alice_robot: RecordingRobot) -> None:
    """Alice's robot streams and changes state: Bob's live feed must carry none of it."""
    alice, bob = Listener(world.ws, world.tokens["alice"]), Listener(world.ws, world.tokens["bob"])
    try:
        alice_robot.ws.send(
            json.dumps(
                {"event": "skill_status", "id": f"alice-status-{RUN}", "data": {"skill": SKILL, "status": "stopped"}}
            )
        )
        for i in range(10):
            point = {"name": "cpu", "value": i / 10, "ts": time.time()}
            alice_robot.ws.send(
                json.dumps({"event": "metrics", "id": f"alice-live-{i}-{RUN}", "data": {"metrics": [point]}})
            )
            time.sleep(0.1)
        time.sleep(1.0)  # the live feed pushes every ~100 ms
    finally:
        alice.close()
        bob.close()
    if not any('"metrics"' in got and "alice-bot" in got for got in alice.frames):
        # The positive control: were alice-bot's points not streamed at all, Bob's silence would prove nothing.
        tally.judge("ws-client-feed", "alice's own feed", True, "alice's feed carried none of alice-bot's points")
    leaked = [got[:150] for got in bob.frames if "alice-bot" in got]
    tally.judge("ws-client-feed", "alice-bot's live metrics and state on bob's feed", bool(leaked), str(leaked[:1]))


def websocket_robot_attempts(world: World, tally: Tenancy) -> None:
    """As bob-bot on /ws/robot/: logging in as alice-bot, and every frame speaking for alice-bot, are refused."""
    from websockets.sync.client import connect

    from bridgeos_agent import protocol
    from bridgeos_agent.protocol import Direction

    with connect(world.ws + "/ws/robot/") as ws:
        ws.send(
            json.dumps(
                {
                    "event": "authentication_robot",
                    "id": "auth",
                    "data": {"robot": "alice-bot", "token": world.robot_tokens["bob-bot"]},
                }
            )
        )
        answer = json.loads(ws.recv(timeout=10))
        tally.judge(
            "ws-robot",
            "bob-bot's token logging in as alice-bot",
            answer["event"] != "authentication_failure",
            str(answer)[:200],
        )
    with connect(world.ws + "/ws/robot/") as ws:
        ws.send(
            json.dumps(
                {
                    "event": "authentication_robot",
                    "id": "auth",
                    "data": {"robot": "bob-bot", "token": world.robot_tokens["bob-bot"]},
                }
            )
        )
        assert json.loads(ws.recv(timeout=10))["event"] == "authentication_success"
        for event in sorted(protocol.EVENTS):
            if (
                not protocol.is_allowed(event, Direction.ROBOT_TO_CLOUD)
                or event in ("ack", "error_message")
                or event.startswith("authentication_")
            ):
                continue
            model = protocol.PAYLOADS.get(event)
            if model is None or "robot" not in model.model_fields:
                continue
            data = valid_data(event, "alice-bot")
            if data is None:
                data = {"robot": "alice-bot", "skill": SKILL}
            ws.send(json.dumps({"event": event, "id": f"x-{event}", "data": data}))
            while True:
                answer = json.loads(ws.recv(timeout=10))
                if answer["event"] in protocol.REQUIRES_ACK:
                    ws.send(protocol.encode(protocol.ack_frame(answer["id"], now=time.time())))
                if answer.get("reply_to") == f"x-{event}":
                    break
            refused = answer["event"] == "error_message"
            tally.judge("ws-robot", f"bob-bot sending {event} for alice-bot", not refused, json.dumps(answer)[:200])


def cross_tenant_outcome(world: World) -> Outcome:
    """Every door, as Bob and as bob-bot, on alice-bot: count the attempts and what got through."""
    alice_robot = RecordingRobot(world.ws, "alice-bot", world.robot_tokens["alice-bot"])
    time.sleep(0.5)  # the connect-time frames (connection_established, robot_config) arrive first
    try:
        before = snapshot()
        started = time.monotonic()
        tally, unclassified = cross_tenant(world, alice_robot)
        diff = changed(before, snapshot())
        # Last, as it changes alice-bot's state on purpose (its own metrics and skill status).
        live_feed_attempt(world, tally, alice_robot)
    finally:
        alice_robot.close()
    expected_doors = {"rest", "page", "components-api", "robots-in-body", "ws-client", "ws-robot", "ws-client-feed"}
    missing = expected_doors - set(tally.doors)
    untried = published_robot_routes() - tally.routes
    passed = tally.allowed == 0 and not diff and not unclassified and not missing and not untried
    return Outcome(
        scenario=NAME,
        injected="cross-tenant: bob and bob-bot on alice-bot through every door",
        sent=tally.attempts,
        passed=passed,
        detail=(
            f"{tally.attempts} attempts in {time.monotonic() - started:.1f} s by door {dict(tally.doors)}; "
            f"{len(tally.routes)} robot routes; {tally.allowed} allowed"
            + (f"; published robot routes never tried: {sorted(untried)}" if untried else "")
            + (f": {tally.holes[:10]}" if tally.holes else "")
            + (f"; routes with no rule: {unclassified}" if unclassified else "")
            + (f"; doors never tried: {sorted(missing)}" if missing else "")
            + (f"; tables changed: {diff}" if diff else "")
        ),
        figures={"cross_tenant_attempts": tally.attempts, "cross_tenant_allowed": tally.allowed},
    )


# --------------------------------------------------------------------------- the scenario


def run(quick: bool) -> list[Outcome]:
    """Play the three parts against one daphne of the scenario's own."""
    logging.getLogger("httpx").setLevel(logging.WARNING)  # a line per request would drown the table
    env = cloud_env()
    daphne = start_daphne(env, NAME, LIMITS_OFF)
    try:
        world = make_world(f"http://127.0.0.1:{daphne.port}", daphne.ws_url)
        outcomes = [cross_tenant_outcome(world)]
        outcomes += fuzz_outcomes(world, daphne, 1_000 if quick else 10_000)
        outcomes.append(schemathesis_outcome(world, daphne, 3 if quick else 50))
        return outcomes
    finally:
        daphne.stop()
