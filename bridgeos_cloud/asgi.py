"""ASGI entry point: Django for HTTP, Channels consumers for WebSockets."""

from __future__ import annotations

import gc
import os

import django

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "bridgeos_cloud.settings")
# Django must be set up before anything imports models (the consumers do).
django.setup(set_prefix=False)

from django.conf import settings  # noqa: E402

from bridgeos_cloud.handler import PooledASGIHandler  # noqa: E402

django_asgi_app = PooledASGIHandler(threads=settings.BRIDGEOS["HTTP_THREADS"])

from channels.routing import ProtocolTypeRouter, URLRouter  # noqa: E402

from bridgeos_cloud.routing import BrowserOriginValidator, websocket_urlpatterns  # noqa: E402

application = ProtocolTypeRouter(
    {
        "http": django_asgi_app,
        "websocket": BrowserOriginValidator(URLRouter(websocket_urlpatterns)),
    }
)

# Everything loaded so far lives as long as the process: move it out of the collector's
# sight, so a full collection walks only what requests allocate (no 100 ms pauses).
gc.freeze()
