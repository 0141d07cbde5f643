"""GET /api/robot/<id>/vpn: a robot's OpenVPN profile, for the robot itself (its token) or its owner."""

from __future__ import annotations

from typing import Any

from django.http import HttpResponse
from drf_spectacular.utils import OpenApiResponse, extend_schema
from rest_framework.authentication import SessionAuthentication
from rest_framework.exceptions import AuthenticationFailed, NotFound, Throttled
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from monitoring.services import record_event
from robots import access
from robots import services as robots
from robots.authentication import ApiTokenAuthentication
from robots.models import TOKEN_PREFIX, Robot
from teams.roles import Right

from .. import services


def robot_from_token(request: Request, robot_id: str) -> Robot | None:
    """Return the robot whose token the request carries, None without one; refuse a wrong one (rate limited)."""
    header = request.META.get("HTTP_AUTHORIZATION", "")
    scheme, _, key = header.partition(" ")
    if scheme.lower() != "token" or not key.startswith(TOKEN_PREFIX):
        return None
    try:
        robot = robots.login_robot(robot_id, key.strip(), request.META.get("REMOTE_ADDR", ""))
    except robots.LoginBlocked as exc:
        raise Throttled(wait=exc.retry_s, detail="Too many failed attempts for this robot; try again later.") from None
    if robot is None:
        raise AuthenticationFailed("Unknown robot or wrong token.")
    return robot


class RobotVpnView(APIView):
    """A robot's OpenVPN profile (certificate and key inline): for the robot (its token), its admins or staff."""

    authentication_classes = [ApiTokenAuthentication, SessionAuthentication]
    permission_classes: list[Any] = []

    def initial(self, request: Request, *args: Any, **kwargs: Any) -> None:
        # A robot token is checked here rather than by DRF's authenticators: it is valid for this robot only.
        self.robot = robot_from_token(request, kwargs["robot_id"])
        if self.robot is None:
            super().initial(request, *args, **kwargs)
            if not request.user or not request.user.is_authenticated:
                raise AuthenticationFailed("Send the robot's token, or an API token of an admin of its organization.")
        else:
            self.format_kwarg = self.get_format_suffix(**kwargs)
            request.accepted_renderer, request.accepted_media_type = self.perform_content_negotiation(request)

    @extend_schema(
        responses={
            (200, "application/x-openvpn-profile"): OpenApiResponse(description="The OpenVPN profile"),
            401: OpenApiResponse(description="No credentials, or wrong ones"),
            404: OpenApiResponse(description="No such robot (or not yours)"),
            409: OpenApiResponse(description="This cloud offers no VPN"),
            429: OpenApiResponse(description="Too many failed attempts"),
        }
    )
    def get(self, request: Request, robot_id: str) -> HttpResponse | Response:
        if self.robot is not None:
            robot, who = self.robot, f"robot {robot_id}"
        else:
            # The profile holds the robot's VPN key: an admin's, like the robot's token.
            robot = access.robot_for(access.actor_of(request), robot_id, Right.ADMINISTER)
            who = f"user {request.user.get_username()}"
        try:
            profile = services.client_profile(robot)
        except services.VpnUnavailable as exc:
            return Response({"detail": str(exc)}, status=409)
        except Robot.DoesNotExist:
            raise NotFound("No such robot.") from None
        record_event(f"VPN profile of robot {robot.id} fetched by {who}", robot_id=robot.id, kind="vpn_profile_fetched")
        response = HttpResponse(profile, content_type="application/x-openvpn-profile")
        response["Content-Disposition"] = f'attachment; filename="{robot.id}.ovpn"'
        response["Cache-Control"] = "no-store"
        return response
