"""Attack (c): Bob and bob-bot on alice-bot through every door, a viewer of Alice's beyond reading, and the tally."""

from __future__ import annotations

import json
import re
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from benchmarks.chaos import Outcome
from benchmarks.chaos.hostile.fuzz import valid_data
from benchmarks.chaos.hostile.rules import (
    FLEET_COMMANDS,
    NO_ROBOT,
    PRIVILEGED_READS,
    ROBOTS_IN_BODY,
    bridge_routes,
    destructive_rank,
    fill_route,
    http_routes,
    is_read_request,
    methods_of,
    published_robot_routes,
)
from benchmarks.chaos.hostile.world import NAME, RUN, SKILL, Listener, RecordingRobot, World
from benchmarks.chaos.rig import changed, snapshot

# HTTP answers that refuse: unauthenticated, forbidden, or a robot the caller may not know of.
REFUSED = {401, 403, 404}


@dataclass
class Tenancy:
    """What Bob, and a viewer of Alice's beyond reading, tried on alice-bot door by door; what got through."""

    attempts: int = 0
    allowed: int = 0
    holes: list[str] = field(default_factory=list)
    doors: Counter = field(default_factory=Counter)
    routes: set[str] = field(default_factory=set)  # robot routes tried, spelled as in the OpenAPI schema
    # The second pair: a member of Alice's organization whose role falls short of the door.
    role_attempts: int = 0
    role_allowed: int = 0
    role_doors: Counter = field(default_factory=Counter)
    # The member's reads that were refused: her role holds them, so each is a door refusing too much.
    reads_refused: list[str] = field(default_factory=list)
    reads: int = 0

    def judge(self, door: str, what: str, allowed: bool, detail: str = "", *, role: bool = False) -> None:
        if role:
            self.role_attempts += 1
            self.role_doors[door] += 1
            self.role_allowed += allowed
        else:
            self.attempts += 1
            self.doors[door] += 1
            self.allowed += allowed
        if allowed:
            self.holes.append(f"{what}: {detail}"[:300])

    def read(self, what: str, answered: bool, detail: str = "") -> None:
        self.reads += 1
        if not answered:
            self.reads_refused.append(f"{what}: {detail}"[:300])


def bridge_handshakes(
    world: World, route: str, tally: Tenancy, callers: dict[str, dict[str, str]], *, role: bool = False
) -> None:
    """Open a bridge door of alice-bot as each caller (across tenants also a forged ticket): each must be refused."""
    from websockets.exceptions import InvalidStatus
    from websockets.sync.client import connect

    url = world.ws + "/" + re.sub(r"<(?:\w+:)?robot_id>", "alice-bot", route)
    tries = [(who, url, headers) for who, headers in callers.items()]
    if not role:
        tries.append(("a forged ticket", url + "?ticket=" + "f" * 43, {}))
    for who, address, headers in tries:
        try:
            with connect(
                address, additional_headers=headers, subprotocols=["foxglove.websocket.v1"], open_timeout=10
            ) as websocket:
                allowed, detail = True, f"opened ({websocket.subprotocol})"
        except InvalidStatus as exc:
            allowed, detail = exc.response.status_code not in REFUSED, f"{exc.response.status_code}"
        tally.judge("bridge", f"WS /{route} of alice-bot as {who}", allowed, detail, role=role)


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
                if route in ("", "fleet/page"):
                    # The fleet's search spans the whole fleet the caller sees, never beyond it. Its text is
                    # echoed back, so it names no robot: "alice" would match alice-bot were it Bob's.
                    attempt("page", "GET", f"/{route}?q=alice", client=session)
            else:
                unclassified.append(route)
        session.close()
    websocket_client_attempts(world, tally, alice_robot)
    websocket_robot_attempts(world, tally)
    return tally, unclassified


def client_session(world: World, token: str) -> Any:
    """Open /ws/client/ and authenticate with an API token; the open connection, as a context manager."""
    from websockets.sync.client import connect

    ws = connect(world.ws + "/ws/client/", max_size=2**22)
    ws.send(json.dumps({"event": "authentication_client", "id": "auth", "data": {"token": token}}))
    assert json.loads(ws.recv(timeout=10))["event"] == "authentication_success"
    return ws


def client_requests() -> list[str]:
    """Every event a client may send that asks something of a robot (authentication and acks aside)."""
    from bridgeos_agent import protocol
    from bridgeos_agent.protocol import Direction

    return [
        event
        for event in sorted(protocol.EVENTS)
        if protocol.is_allowed(event, Direction.CLIENT_TO_CLOUD)
        and event not in ("ack", "error_message")
        and not event.startswith("authentication_")
    ]


def websocket_client_attempts(world: World, tally: Tenancy, alice_robot: RecordingRobot) -> None:
    """As Bob on /ws/client/: every request naming alice-bot is refused, and nothing of alice-bot streams to him."""
    from bridgeos_agent import protocol

    with client_session(world, world.tokens["bob"]) as ws:
        for event in client_requests():
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


def cross_role(world: World, alice_robot: RecordingRobot, tally: Tenancy, member: str = "vera") -> None:
    """Try every door needing more than reading as a viewer of alice-bot's organization; her reads must be answered.

    ``member`` names who plays the viewer: the tests hand it Otto, an operator there, whose
    commands must then count as allowed, to prove this tally counts an access that is granted.
    """
    import httpx

    api = {"Authorization": f"Token {world.tokens[member]}"}
    with httpx.Client(base_url=world.http, timeout=15, headers=api) as http:
        calls = [
            (route, method)
            for route, callback in http_routes()
            if "robot_id" in route and route.startswith("api/")
            for method in methods_of(callback)
        ]
        calls += [(route, "POST") for route in FLEET_COMMANDS]
        # What would destroy alice-bot or cut its link, were it let through, goes last: it would spoil the rest.
        calls.sort(key=destructive_rank)
        for route, method in calls:
            url = fill_route(route, world, "alice-bot", "")
            what = f"{method} {url} as {member}"
            if method == "GET" and route not in PRIVILEGED_READS:
                response = http.get(url)
                # Answered, if not always with 200 (a recording whose file is not assembled yet is a 409).
                answered = response.status_code not in REFUSED
                tally.read(what, answered, f"{response.status_code} {response.text[:120]}")
                continue
            seen = alice_robot.count()
            body = {"location": "cloud", "skill": SKILL, "template": world.template_id, "name": "taken"}
            response = http.request(method, "/" + route if route in FLEET_COMMANDS else url, json=body)
            reached = alice_robot.commands_since(seen)
            if response.status_code == 405:
                continue
            if route in FLEET_COMMANDS:
                # Answered with the robots the caller may command: a viewer's answer names none of them.
                door, allowed = "fleet", bool(reached) or "alice-bot" in response.text
            else:
                door, allowed = "rest", bool(reached) or response.status_code != 403
            detail = f"{response.status_code} {response.text[:120]} reached={reached[:1]}"
            tally.judge(door, what, allowed, detail, role=True)
        if member in world.sessions:
            with httpx.Client(base_url=world.http, timeout=15, cookies={"sessionid": world.sessions[member]}) as page:
                response = page.get("/robots/alice-bot/")
            shown = response.status_code == 200 and "alice-bot" in response.text
            tally.read(f"GET /robots/alice-bot/ as {member}", shown, f"{response.status_code}")
    for route in bridge_routes():
        bridge_handshakes(world, route, tally, {member: api}, role=True)
    websocket_client_roles(world, tally, alice_robot, member)


def websocket_client_roles(world: World, tally: Tenancy, alice_robot: RecordingRobot, member: str) -> None:
    """As a member on /ws/client/: every request that changes alice-bot is refused as forbidden, every read answered."""
    from bridgeos_agent import protocol

    with client_session(world, world.tokens[member]) as ws:
        for event in client_requests():
            what = f"{event} for alice-bot as {member}"
            data = valid_data(event, "alice-bot")
            if data is None:
                tally.judge(
                    "ws-client", f"{what} (no valid request)", True, "the payload filler needs teaching", role=True
                )
                continue
            seen = alice_robot.count()
            ws.send(json.dumps({"event": event, "id": f"r-{event}", "data": data}))
            while True:
                # Alice-bot's live feed reaches a member too: only the answer ends the wait.
                answer = json.loads(ws.recv(timeout=30))
                if answer["event"] in protocol.REQUIRES_ACK:
                    ws.send(protocol.encode(protocol.ack_frame(answer["id"], now=time.time())))
                if answer.get("reply_to") == f"r-{event}":
                    break
            detail = json.dumps(answer)[:200]
            if is_read_request(event):
                tally.read(what, answer["event"] != "error_message", detail)
                continue
            refused = answer["event"] == "error_message" and answer["data"].get("code") == "forbidden"
            tally.judge("ws-client", what, not refused or bool(alice_robot.commands_since(seen)), detail, role=True)


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
        cross_role(world, alice_robot, tally)
        diff = changed(before, snapshot())
        # Last, as it changes alice-bot's state on purpose (its own metrics and skill status).
        live_feed_attempt(world, tally, alice_robot)
    finally:
        alice_robot.close()
    expected_doors = {"rest", "page", "components-api", "robots-in-body", "ws-client", "ws-robot", "ws-client-feed"}
    missing = expected_doors - set(tally.doors)
    untried = published_robot_routes() - tally.routes
    missing_roles = {"rest", "fleet", "bridge", "ws-client"} - set(tally.role_doors)
    passed = (
        tally.allowed == 0
        and tally.role_allowed == 0
        and not tally.reads_refused
        and not diff
        and not unclassified
        and not missing
        and not missing_roles
        and not untried
    )
    return Outcome(
        scenario=NAME,
        injected="cross-tenant: bob and bob-bot on alice-bot through every door; a viewer of alice's beyond reading",
        sent=tally.attempts,
        passed=passed,
        detail=(
            f"{tally.attempts} attempts in {time.monotonic() - started:.1f} s by door {dict(tally.doors)}; "
            f"{len(tally.routes)} robot routes; {tally.allowed} allowed; "
            f"as a viewer {tally.role_attempts} attempts by door {dict(tally.role_doors)}, "
            f"{tally.role_allowed} allowed, "
            f"{tally.reads - len(tally.reads_refused)} of {tally.reads} reads answered"
            + (f"; reads refused: {tally.reads_refused[:10]}" if tally.reads_refused else "")
            + (f"; role doors never tried: {sorted(missing_roles)}" if missing_roles else "")
            + (f"; published robot routes never tried: {sorted(untried)}" if untried else "")
            + (f": {tally.holes[:10]}" if tally.holes else "")
            + (f"; routes with no rule: {unclassified}" if unclassified else "")
            + (f"; doors never tried: {sorted(missing)}" if missing else "")
            + (f"; tables changed: {diff}" if diff else "")
        ),
        figures={
            "cross_tenant_attempts": tally.attempts,
            "cross_tenant_allowed": tally.allowed,
            "cross_role_attempts": tally.role_attempts,
            "cross_role_allowed": tally.role_allowed,
        },
    )
