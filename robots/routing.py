"""WebSocket routes of robots: where Robot Controllers connect."""

from __future__ import annotations

from django.urls import path

from .consumers import RobotConsumer

websocket_urlpatterns = [path("ws/robot/", RobotConsumer.as_asgi())]
