"""WebSocket routes of robots: where Robot Controllers connect."""

from __future__ import annotations

from django.urls import path

from .bridges import FoxgloveConsumer, RosbridgeConsumer
from .consumers import RobotConsumer

websocket_urlpatterns = [
    path("ws/robot/", RobotConsumer.as_asgi()),
    path("ws/rosbridge/<slug:robot_id>/", RosbridgeConsumer.as_asgi()),
    path("ws/foxglove/<slug:robot_id>/", FoxgloveConsumer.as_asgi()),
]

# Doors that never read the session cookie (an API token or a ticket only): pages of other origins
# (Foxglove's web app, a roslibjs page) may open them, with no cross-site hijacking to fear.
CROSS_ORIGIN_PATHS = ("/ws/rosbridge/", "/ws/foxglove/")
