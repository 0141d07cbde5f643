"""HTTP Basic for the token server: a user's password or API token, or a robot's id and token."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from rest_framework.exceptions import AuthenticationFailed, Throttled

from robots.access import API_TOKEN_PREFIX, api_token
from robots.authentication import PasswordAuthentication
from robots.models import TOKEN_PREFIX
from robots.services import LoginBlocked, login_robot

REALM = "bridgeOS registry"


@dataclass(frozen=True)
class RobotIdentity:
    """The ``request.user`` of a robot asking for a registry token: authenticated, never staff."""

    robot_id: str
    is_authenticated: bool = True
    is_active: bool = True
    is_staff: bool = False
    pk: None = None

    def get_username(self) -> str:
        return f"robot:{self.robot_id}"


class RegistryAuthentication(PasswordAuthentication):
    """Tell the credential by its token's prefix: `bat_` an API token, `brt_` a robot's token, else a password.

    A robot authenticates as itself (``request.auth``), so the grant rules hold it to its
    organization's pulls.
    """

    www_authenticate_realm = REALM

    def authenticate_credentials(self, userid: str, password: str, request: Any = None) -> tuple[Any, Any]:
        if "\x00" in userid or "\x00" in password:
            # PostgreSQL cannot even look such a name up (it would be a 500).
            raise AuthenticationFailed("Invalid username/password.")
        if password.startswith(API_TOKEN_PREFIX):
            token = api_token(password)
            if token is None or token.user.get_username() != userid:
                raise AuthenticationFailed("Invalid or expired API token for this user.")
            return token.user, token
        if password.startswith(TOKEN_PREFIX):
            address = request.META.get("REMOTE_ADDR", "") if request is not None else ""
            try:
                robot = login_robot(userid, password, address)
            except LoginBlocked as exc:
                raise Throttled(wait=exc.retry_s, detail="Too many failed logins; try again later.") from None
            if robot is None:
                raise AuthenticationFailed("Invalid robot id/token.")
            return RobotIdentity(robot.id), robot
        return super().authenticate_credentials(userid, password, request)
