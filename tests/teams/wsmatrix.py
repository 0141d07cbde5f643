"""The role matrix's WebSocket doors over a real socket: /ws/client/'s requests, the bridges' handshakes, /ws/robot/."""

from __future__ import annotations

import json
import time
import uuid
from typing import Any

from websockets.exceptions import InvalidStatus
from websockets.sync.client import ClientConnection, connect

from teams.roles import RANK, Right, Role
from tests.teams.matrix import CALLERS, CLIENT_EVENTS, LEAST, ROLES, TARGETS, Tally, World

# What a request a caller may make answers on the matrix's robot, which is offline: a command
# is refused as such, a setting is stored and acked (the robot takes it when it connects).
CLIENT_ANSWERS: dict[str, str] = {
    "robot_start": "error:robot_offline",
    "robot_stop": "error:robot_offline",
    "shutdown": "error:robot_offline",
    "robot_config_get": "robot_config",
    "robot_config_update": "ack",
    "offloading": "ack",
    "offloading_get": "offloading",
    "skill_start": "error:robot_offline",
    "skill_stop": "error:robot_offline",
    "skill_status_get": "skill_status",
    "skill_config_get": "skill_config",
    "component_start": "error:robot_offline",
    "component_stop": "error:robot_offline",
    "component_status_get": "component_status",
    "component_migrate": "error:robot_offline",
    "metrics_get": "metrics",
    # A tail's first answer: each component's stored lines, or an ack when the robot has no component yet.
    "logs_subscribe": "ack",
    "logs_unsubscribe": "ack",
    "metrics_subscribe": "ack",
}
# Requests that only read without a _get in their name: live tails and the live metrics' subscription.
READS = ("logs_subscribe", "logs_unsubscribe", "metrics_subscribe")
# A refused WebSocket handshake is a 403 whatever the reason (daphne has no other status for
# it): no role, another organization's robot and a missing one answer alike.
BRIDGE_REFUSED = 403


def answer_to(ws: ClientConnection, frame_id: str) -> dict[str, Any]:
    """Read frames until the one that answers ``frame_id``."""
    while True:
        frame = json.loads(ws.recv(timeout=10))
        if frame.get("reply_to") == frame_id:
            return frame


def entries() -> int:
    """The audit trail's length now."""
    from audit.models import AuditEntry

    return AuditEntry.objects.count()


def settled(before: int, expected: int) -> int:
    """The entries written since ``before``, waiting a moment for a door that writes after it answers."""
    deadline = time.monotonic() + 2
    while (written := entries() - before) < expected and time.monotonic() < deadline:
        time.sleep(0.02)
    return written


def outcome(frame: dict[str, Any]) -> str:
    """An answer as the matrix writes it: its event, or `error:<code>`."""
    if frame["event"] == "error_message":
        return f"error:{frame['data'].get('code')}"
    return frame["event"]


def client_expected(event: str, caller: str, target: str) -> str:
    """What a client's request answers a caller on a target organization's robot."""
    from dashboard.consumers import right_for

    if caller == "none" or target == "other":
        return "error:not_found"
    right: Right = right_for(event)  # type: ignore[arg-type]
    return CLIENT_ANSWERS[event] if RANK[Role(caller)] >= RANK[Role(LEAST[right])] else "error:forbidden"


def client_data(event: str, robot_id: str, payload: dict[str, Any]) -> dict[str, Any]:
    """The data of a client's request about a robot: named in ``robot``, or in ``robots`` for a subscription."""
    if event == "metrics_subscribe":
        return {"robots": [robot_id], **payload}
    return {"robot": robot_id, **payload}


def ask_client(world: World, tally: Tally, ws_url: str) -> None:
    """Send every client request as every caller on both organizations' robots."""
    for caller in CALLERS:
        with connect(f"{ws_url}/ws/client/", open_timeout=10) as ws:
            ident = uuid.uuid4().hex
            data = {"token": world.tokens[caller]} if caller in world.tokens else {}
            ws.send(json.dumps({"event": "authentication_client", "id": ident, "data": data}))
            signed_in = outcome(answer_to(ws, ident))
            tally.judge(
                f"{caller} WS /ws/client/ authentication",
                signed_in,
                "authentication_failure" if caller == "anonymous" else "authentication_success",
            )
            if caller == "anonymous":
                continue
            for event, payload in sorted(CLIENT_EVENTS.items()):
                for target in TARGETS:
                    ident = uuid.uuid4().hex
                    frame = {"event": event, "id": ident, "data": client_data(event, world.robot_id(target), payload)}
                    before = entries()
                    ws.send(json.dumps(frame))
                    got = outcome(answer_to(ws, ident))
                    tally.judge(f"{caller} WS {event} on {target}", got, client_expected(event, caller, target))
                    # Reads (the _get requests, live log tails and subscriptions) leave no entry in the audit trail.
                    if not event.endswith("_get") and event not in READS:
                        tally.judge(f"{caller} WS {event} on {target} audit entries", settled(before, 1), 1)


def ask_bridges(world: World, tally: Tally, ws_url: str) -> None:
    """Open each bridge on both organizations' robots as every caller."""
    for route, subprotocols in (("rosbridge", None), ("foxglove", ["foxglove.websocket.v1"])):
        for caller in CALLERS:
            for target in TARGETS:
                headers = {"Authorization": f"Token {world.tokens[caller]}"} if caller in world.tokens else {}
                url = f"{ws_url}/ws/{route}/{world.robot_id(target)}/"
                before = entries()
                try:
                    with connect(url, additional_headers=headers, subprotocols=subprotocols, open_timeout=10):  # type: ignore[arg-type]
                        status = 101
                except InvalidStatus as exc:
                    status = exc.response.status_code
                may = caller in ROLES and target == "own" and RANK[Role(caller)] >= RANK[Role.OPERATOR]
                want = 101 if may else BRIDGE_REFUSED
                tally.judge(f"{caller} WS /ws/{route}/ on {target}", status, want)
                # A bridge session opened or refused, a stranger's too, is one entry.
                tally.judge(f"{caller} WS /ws/{route}/ on {target} audit entries", settled(before, 1), 1)


def ask_robot_door(world: World, tally: Tally, ws_url: str) -> None:
    """Log in on /ws/robot/ as each target's robot with every caller's token: only the robot's own passes."""
    for target in TARGETS:
        robot_id = world.robot_id(target)
        keys = {caller: world.tokens.get(caller, "") for caller in CALLERS if caller in world.tokens}
        keys["the robot"] = world.robot_tokens[robot_id]
        for who, key in keys.items():
            with connect(f"{ws_url}/ws/robot/", open_timeout=10) as ws:
                ident = uuid.uuid4().hex
                ws.send(
                    json.dumps(
                        {"event": "authentication_robot", "id": ident, "data": {"robot": robot_id, "token": key}}
                    )
                )
                got = outcome(answer_to(ws, ident))
            want = "authentication_success" if who == "the robot" else "authentication_failure"
            tally.judge(f"{who} WS /ws/robot/ as {robot_id}", got, want)


def ask_websockets(world: World, tally: Tally, ws_url: str) -> None:
    """Ask every WebSocket door of the matrix."""
    ask_client(world, tally, ws_url)
    ask_bridges(world, tally, ws_url)
    ask_robot_door(world, tally, ws_url)
