"""Relay a command from a REST request to robots and turn the outcome into a response."""

from __future__ import annotations

from typing import Any

from asgiref.sync import async_to_sync
from django.conf import settings
from django.db import connection
from rest_framework import status
from rest_framework.exceptions import ValidationError
from rest_framework.request import Request
from rest_framework.response import Response

from bridgeos_agent.protocol import Envelope, Event, ProtocolError

from .. import services

MAX_WAIT_S = 60.0


def wait_seconds(request: Request) -> float:
    """Read `?wait=` seconds (default from settings, at most a minute)."""
    raw = request.query_params.get("wait")
    if raw is None:
        return settings.BRIDGEOS["COMMAND_WAIT_S"]
    try:
        wait = float(raw)
    except ValueError:
        raise ValidationError({"wait": ["A number of seconds."]}) from None
    if not 0 < wait <= MAX_WAIT_S:
        raise ValidationError({"wait": [f"Between 0 and {MAX_WAIT_S:g} seconds."]})
    return wait


def release_connection() -> None:
    """Give this thread's database connection back before waiting seconds on robots."""
    if not connection.in_atomic_block:
        connection.close()


def _result(robot_id: str, event: Event, reply: Envelope) -> dict[str, Any]:
    return {
        "robot": robot_id,
        "event": str(event),
        "accepted": reply.event != Event.ERROR_MESSAGE,
        "reply": {"event": reply.event, "data": reply.data},
    }


def relay(robot_id: str, event: Event, data: dict[str, Any], wait: float) -> Response:
    """Relay one command to a robot and answer with its reply, 409 if offline, 504 on timeout."""
    release_connection()
    try:
        reply = async_to_sync(services.relay_command)(robot_id, event, data, wait=wait)
    except ProtocolError as exc:
        raise ValidationError({exc.field or "non_field_errors": [exc.message]}) from None
    except services.RobotOffline:
        return Response(
            {"detail": f"Robot {robot_id} is offline; connect it and try again."}, status=status.HTTP_409_CONFLICT
        )
    except services.CommandTimeout as exc:
        return Response({"detail": str(exc)}, status=status.HTTP_504_GATEWAY_TIMEOUT)
    return Response(_result(robot_id, event, reply))


def relay_to_fleet(robot_ids: list[str], event: Event, wait: float) -> Response:
    """Relay one command to many robots at once and report each robot's outcome."""
    release_connection()
    outcomes = async_to_sync(services.relay_to_many)(robot_ids, event, {}, wait=wait)
    results = []
    for robot_id in robot_ids:
        outcome = outcomes[robot_id]
        if isinstance(outcome, services.RobotOffline):
            results.append({"robot": robot_id, "accepted": False, "error": "offline"})
        elif isinstance(outcome, services.CommandTimeout):
            results.append({"robot": robot_id, "accepted": False, "error": f"no answer within {wait:g} s"})
        else:
            result = _result(robot_id, event, outcome)
            del result["event"]
            results.append(result)
    return Response({"results": results})
