"""What daphne's stack (Twisted, autobahn) is told in a bridgeOS server process, each measured with py-spy.

Each tuning changes how much work the same traffic costs, never what goes over the wire: a
robot or a browser cannot tell a tuned process from an untuned one.
"""

from __future__ import annotations

import sys
import time
from typing import Any


def tune_daphne() -> None:
    """Apply every tuning whose module daphne has loaded (none in a test's in-process server)."""
    uncoloured_autobahn_logs()
    lazy_autobahn_handshake_log()
    heartbeats_count_as_traffic()
    write_through_when_idle()
    fewer_garbage_collections()


def uncoloured_autobahn_logs() -> None:
    """Stop autobahn colouring its debug-log arguments: it does so for every frame daphne sends."""
    # autobahn formats each sent frame's log.debug arguments with click colours before the logger
    # drops them: 12 % of daphne's CPU under a rosbridge flood (py-spy). Plain, they cost almost nothing.
    util = sys.modules.get("autobahn.util")
    if util is not None and hasattr(util, "_HAS_CLICK"):
        util._HAS_CLICK = False


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


def heartbeats_count_as_traffic() -> None:
    """Have daphne take a robot's own heartbeat (a WebSocket ping) as a sign of life, as it takes a frame."""
    # daphne pings every connection silent for --ping-interval and counts only data frames as
    # traffic, so it pinged every robot that was already pinging it: at 10,000 robots, 1,000 more
    # pings and pongs a second. A robot that vanishes stops pinging and is pinged, then dropped.
    module = sys.modules.get("daphne.ws_protocol")
    if module is None or getattr(module.WebSocketProtocol, "_bridgeos_pings_are_traffic", False):
        return
    answer = module.WebSocketProtocol.onPing

    def on_ping(self: module.WebSocketProtocol, payload: bytes) -> None:  # type: ignore[name-defined]
        self.last_ping = time.time()
        answer(self, payload)

    module.WebSocketProtocol.onPing = on_ping
    module.WebSocketProtocol._bridgeos_pings_are_traffic = True


def write_through_when_idle() -> None:
    """Have a TCP connection with nothing queued send at once, as asyncio's transports do, not a loop turn later."""
    # Twisted queues every write and registers the socket for writability (two epoll_ctl calls and a
    # loop turn per frame through the asyncio reactor): a third of an idle fleet's cost in daphne is
    # the pongs to 2,000 heartbeats a second going that way. Anything already queued keeps its order,
    # and a producer (HTTPChannel registers one) is paused only by what is queued, as before.
    tcp = sys.modules.get("twisted.internet.tcp")
    if tcp is None or getattr(tcp.Connection, "_bridgeos_write_through", False):
        return
    queued_write = tcp.Connection.write

    def write(self: Any, data: bytes) -> None:
        if (
            type(data) is bytes
            and data
            and self.connected
            and not self.TLS
            and not self.disconnecting
            and not self._writeDisconnected
            and not self._tempDataBuffer
            and self.offset == len(self.dataBuffer)
        ):
            sent = self.writeSomeData(data)
            if isinstance(sent, int) and sent > 0:
                if sent == len(data):
                    return
                data = data[sent:]
            # Nothing sent (the socket is full) or the connection is lost: queued, and doWrite finds out.
        queued_write(self, data)

    tcp.Connection.write = write
    tcp.Connection._bridgeos_write_through = True


# Allocations between young collections (CPython's default: 700), and how many collections of each
# generation trigger one of the next (defaults: 10 and 10).
GC_THRESHOLDS = (50_000, 20, 10)


def fewer_garbage_collections() -> None:
    """Collect cycles far less often, and never scan again what the server loaded before it started."""
    # A robot's frame lives from its arrival to its commit, long enough to survive young collections
    # into the old generation, and with thousands of robots connected every full collection walks
    # millions of objects: at 3,000 robots sending 600 metric frames a second, the collector took
    # half of daphne's CPU (gc callbacks), and its pauses held acks back. With these thresholds the
    # same load took 18 % of a core instead of 38 %, and 10,000 robots connected in 9.9 s, not 15.9 s.
    # Garbage without cycles is freed at once as ever; a closed connection's cycles wait a little longer.
    if "daphne.server" not in sys.modules:
        return
    import gc

    gc.freeze()
    gc.set_threshold(*GC_THRESHOLDS)
