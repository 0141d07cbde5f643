"""DRF authentication by the expiring API tokens that /api/auth issues."""

from __future__ import annotations

from typing import Any

from rest_framework.authentication import BasicAuthentication, TokenAuthentication
from rest_framework.exceptions import AuthenticationFailed, Throttled

from bridgeos_cloud import bruteforce
from monitoring.choices import Level
from monitoring.services import record_event

from .access import api_token


class ApiTokenAuthentication(TokenAuthentication):
    """Accept `Authorization: Token <key>` for an unexpired API token (never a robot's token)."""

    def authenticate_credentials(self, key: str) -> tuple[Any, Any]:
        token = api_token(key)
        if token is None:
            raise AuthenticationFailed("Invalid or expired token; get a new one from /api/auth.")
        return token.user, token


class PasswordAuthentication(BasicAuthentication):
    """HTTP Basic, refusing a NUL byte that PostgreSQL cannot even look up (it would fail with a 500)."""

    def authenticate_credentials(self, userid: str, password: str, request: Any = None) -> tuple[Any, None]:
        if "\x00" in userid or "\x00" in password:
            raise AuthenticationFailed("Invalid username/password.")
        address = request.META.get("REMOTE_ADDR", "") if request is not None else ""
        keys = bruteforce.login_keys("user", userid, address)
        limit = bruteforce.failures()
        retry = limit.blocked_for(keys, bruteforce.window())
        if retry:
            raise Throttled(wait=retry, detail="Too many failed logins; try again later.")
        try:
            found = super().authenticate_credentials(userid, password, request)
        except AuthenticationFailed:
            if limit.failed(keys, bruteforce.window()):
                record_event(
                    f"Too many failed logins of user {userid[:150]} from {address}",
                    level=Level.WARNING,
                    kind="authentication_blocked",
                    data={"user": userid[:150], "address": address},
                )
            raise
        limit.succeeded(keys[0][0])
        return found
