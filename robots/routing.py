"""WebSocket routes of robots: where Robot Controllers connect."""

from __future__ import annotations

websocket_urlpatterns: list = []
