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

django_asgi_app = PooledASGIHandler(
    threads=settings.BRIDGEOS["HTTP_THREADS"], write_threads=settings.BRIDGEOS["HTTP_WRITE_THREADS"]
)

from channels.routing import ProtocolTypeRouter, URLRouter  # noqa: E402


def uncoloured_autobahn_logs() -> None:
    """Stop autobahn colouring its debug-log arguments: it does so for every frame daphne sends."""
    # autobahn formats each sent frame's log.debug arguments with click colours before the logger
    # drops them: 12 % of daphne's CPU under a rosbridge flood (py-spy). Plain, they cost almost nothing.
    util = sys.modules.get("autobahn.util")
    if util is not None and hasattr(util, "_HAS_CLICK"):
        util._HAS_CLICK = False


uncoloured_autobahn_logs()


class LazyPformat:
    """Pretty-print an object only if a log line holding it is ever written."""

    def __init__(self, value: object) -> None:
        self.value = value

    def __str__(self) -> str:
        from pprint import pformat

        return pformat(self.value)


def lazy_autobahn_handshake_log() -> None:
    """Stop autobahn pretty-printing every new connection's options for a debug line nobody reads."""
    # autobahn pformats its 40 protocol options on each connection for log.debug, which daphne
    # drops: 40 % of daphne's CPU while 3,000 robots connect at once (py-spy).
    protocol = sys.modules.get("autobahn.websocket.protocol")
    if protocol is not None and getattr(protocol, "pformat", None) is not LazyPformat:
        protocol.pformat = LazyPformat


lazy_autobahn_handshake_log()


def heartbeats_count_as_traffic() -> None:
    """Have daphne take a robot's own heartbeat (a WebSocket ping) as a sign of life, as it takes a frame."""
    # daphne pings every connection silent for --ping-interval and counts only data frames as
    # traffic, so it pinged every robot that was already pinging it: at 10,000 robots, 1,000 more
    # pings and pongs a second. A robot that vanishes stops pinging and is pinged, then dropped.
    module = sys.modules.get("daphne.ws_protocol")
    if module is None or getattr(module.WebSocketProtocol, "_bridgeos_pings_are_traffic", False):
        return
    import time

    answer = module.WebSocketProtocol.onPing

    def on_ping(self: module.WebSocketProtocol, payload: bytes) -> None:  # type: ignore[name-defined]
        self.last_ping = time.time()
        answer(self, payload)

    module.WebSocketProtocol.onPing = on_ping
    module.WebSocketProtocol._bridgeos_pings_are_traffic = True


heartbeats_count_as_traffic()

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
