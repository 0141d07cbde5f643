"""The Components API for cloud copies: their calls relayed to the Skill's manager on the robot.

A cloud copy's ``BRIDGEOS_MANAGER_URL`` points here, with its launch token in the path (a new
one each launch, void once the copy is no longer wanted), so it reaches the same API (thesis
Table 3.2) its robot copy reaches locally, through the robot's own connection.
"""

from __future__ import annotations

import json

from asgiref.sync import sync_to_async
from django.http import HttpRequest, JsonResponse
from django.views.decorators.csrf import csrf_exempt

from bridgeos_agent.protocol import Event, ProtocolError
from robots.services import CommandTimeout, RobotOffline, relay_command

from ..cloud.orchestration import running_copy

WAIT_S = 10.0


@csrf_exempt  # no cookies: the launch token in the path is the credential
async def components_api(request: HttpRequest, token: str, path: str) -> JsonResponse:
    """Relay one Components API call of a cloud copy to its Skill's manager and return the answer."""
    if request.method not in ("GET", "POST"):
        return JsonResponse({"detail": f"method {request.method} not allowed: use GET or POST"}, status=405)
    copy = await sync_to_async(running_copy)(token)
    if copy is None:
        return JsonResponse({"detail": "no cloud copy is running with this launch token"}, status=404)
    robot_id, skill_id, _ = copy
    body = None
    if request.method == "POST":
        try:
            body = json.loads(request.body or b"{}")
        except ValueError:
            return JsonResponse({"detail": "the body is not JSON"}, status=400)
        if not isinstance(body, dict):
            return JsonResponse({"detail": "the body must be a JSON object"}, status=400)
    data = {
        "skill": skill_id,
        "method": request.method,
        "path": f"/{path}",
        "query": request.META.get("QUERY_STRING", ""),
        "body": body,
    }
    try:
        reply = await relay_command(robot_id, Event.COMPONENTS_API, data, wait=WAIT_S)
    except ProtocolError as exc:
        return JsonResponse({"detail": exc.message, "field": exc.field}, status=400)
    except RobotOffline:
        return JsonResponse({"detail": f"robot {robot_id} is offline: its manager cannot be reached"}, status=503)
    except CommandTimeout:
        return JsonResponse({"detail": f"robot {robot_id} did not answer within {WAIT_S:g} s"}, status=504)
    if reply.event != Event.COMPONENTS_API_REPLY:
        status = 404 if reply.data.get("code") == "not_found" else 502
        return JsonResponse({"detail": reply.data.get("message", "the robot refused the call")}, status=status)
    return JsonResponse(reply.data.get("body"), status=int(reply.data["status"]), safe=False)
