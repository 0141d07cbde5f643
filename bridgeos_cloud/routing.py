"""WebSocket routes of every app, behind an Origin check for browsers."""

from __future__ import annotations

from typing import Any
from urllib.parse import urlsplit

from django.conf import settings
from django.http.request import validate_host

from dashboard.routing import websocket_urlpatterns as client_routes
from robots.routing import CROSS_ORIGIN_PATHS
from robots.routing import websocket_urlpatterns as robot_routes

websocket_urlpatterns = [*robot_routes, *client_routes]


class BrowserOriginValidator:
    """Refuse WebSockets opened by a page of a foreign origin; allow clients that send none.

    Browsers always send Origin, so a missing one means a robot or a script that
    authenticates with a token; a foreign one means cross-site WebSocket hijacking.
    """

    def __init__(self, application: Any) -> None:
        self.application = application

    async def __call__(self, scope: dict, receive: Any, send: Any) -> Any:
        origin = dict(scope.get("headers", [])).get(b"origin")
        if scope.get("path", "").startswith(CROSS_ORIGIN_PATHS):
            return await self.application(scope, receive, send)
        if origin is not None and not self.allowed(origin.decode("latin-1")):
            await send({"type": "websocket.close", "code": 4003})
            return None
        return await self.application(scope, receive, send)

    @staticmethod
    def allowed(origin: str) -> bool:
        """Tell whether an Origin header names one of ALLOWED_HOSTS or a trusted origin."""
        if origin in settings.CSRF_TRUSTED_ORIGINS:
            return True
        host = urlsplit(origin).hostname
        return host is not None and validate_host(host, settings.ALLOWED_HOSTS)
