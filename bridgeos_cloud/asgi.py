"""ASGI entry point: Django for HTTP, Channels consumers for WebSockets."""

from __future__ import annotations

import asyncio
import gc
import os
import sys

import django

os.environ.setdefault("DJANGO_SETTINGS_MODULE", "bridgeos_cloud.settings")
# Django must be set up before anything imports models (the consumers do).
django.setup(set_prefix=False)

from django.conf import settings  # noqa: E402

from bridgeos_cloud.handler import PooledASGIHandler  # noqa: E402
from bridgeos_cloud.loopowned import close_loop_objects  # noqa: E402
from bridgeos_cloud.servertuning import tune_daphne  # noqa: E402

django_asgi_app = PooledASGIHandler(
    threads=settings.BRIDGEOS["HTTP_THREADS"], write_threads=settings.BRIDGEOS["HTTP_WRITE_THREADS"]
)

from channels.routing import ProtocolTypeRouter, URLRouter  # noqa: E402

tune_daphne()

from bridgeos_cloud.routing import BrowserOriginValidator, websocket_urlpatterns  # noqa: E402
from robots.presence import start_presence  # noqa: E402

application = ProtocolTypeRouter(
    {
        "http": django_asgi_app,
        "websocket": BrowserOriginValidator(URLRouter(websocket_urlpatterns)),
    }
)


def close_at_shutdown() -> None:
    """Have daphne's reactor register this process at start and close the loop's objects before it stops."""
    reactor = sys.modules.get("twisted.internet.reactor")
    if reactor is None:
        return  # not served by daphne (a test's in-process server): its loop's owner closes nothing

    from twisted.internet.defer import Deferred

    def close() -> Deferred:
        # The reactor runs on the asyncio loop the consumers use: close their objects on it, and wait.
        return Deferred.fromFuture(asyncio.ensure_future(close_loop_objects()))

    reactor.addSystemEventTrigger("before", "shutdown", close)
    # Registered at startup, so this process sweeps up dead processes' robots before it holds any.
    reactor.callWhenRunning(lambda: asyncio.ensure_future(start_presence()))


close_at_shutdown()

# Everything loaded so far lives as long as the process: move it out of the collector's
# sight, so a full collection walks only what requests allocate (no 100 ms pauses).
gc.freeze()
