"""WebSocket routes of the dashboard app: the live feed and commands for dashboards and apps."""

from __future__ import annotations

from channels.auth import AuthMiddlewareStack
from django.urls import path

from .consumers import ClientConsumer

# The session middleware lets a logged-in dashboard authenticate without a token.
websocket_urlpatterns = [path("ws/client/", AuthMiddlewareStack(ClientConsumer.as_asgi()))]
