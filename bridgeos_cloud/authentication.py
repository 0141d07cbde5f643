"""DRF authentication by the expiring API tokens that /api/auth issues."""

from __future__ import annotations

from typing import Any

from rest_framework.authentication import BasicAuthentication, TokenAuthentication
from rest_framework.exceptions import AuthenticationFailed

from robots.services import api_token


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
        return super().authenticate_credentials(userid, password, request)
