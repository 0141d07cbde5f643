"""WebSocket routes of monitoring: the live feed for dashboards and apps."""

from __future__ import annotations

websocket_urlpatterns: list = []
