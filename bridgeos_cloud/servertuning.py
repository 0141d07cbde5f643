"""What daphne's stack (Twisted, autobahn) is told in a bridgeOS server process, each measured with py-spy.

Each tuning changes how much work the same traffic costs, never what goes over the wire beyond how
it is cut into TCP segments: a robot or a browser cannot tell a tuned process from an untuned one.
The one exception is a timeout daphne has no option for: how long a peer may take to answer a close.
"""

from __future__ import annotations

import asyncio
import io
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Any


def tune_daphne() -> None:
    """Apply every tuning whose module daphne has loaded (none in a test's in-process server)."""
    uncoloured_autobahn_logs()
    lazy_autobahn_handshake_log()
    heartbeats_count_as_traffic()
    reads_without_log_context()
    segments_without_debug_lines()
    pings_answered_directly()
    text_frames_read_directly()
    write_through_when_idle()
    fewer_garbage_collections()
    buffered_access_log()
    patient_close_handshakes()
    applications_reaped_when_they_end()
    timeouts_checked_in_one_pass()


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


def reads_without_log_context() -> None:
    """Call a ready socket's handler without Twisted's per-call log context, still logging its failures."""
    # The asyncio reactor calls every ready socket's doRead and doWrite through callWithLogger,
    # which asks the connection for its log prefix and pushes a context for Twisted's legacy log,
    # which daphne sends nowhere: a tenth of what an idle fleet of 10,000 cost daphne (py-spy,
    # 2,000 pings a second). Sockets registered from now on get the leaner call.
    module = sys.modules.get("twisted.internet.asyncioreactor")
    if module is not None:
        module.callWithLogger = call_and_log_failures


def call_and_log_failures(logger: Any, func: Any, *args: Any, **kw: Any) -> Any:
    """Return ``func(*args, **kw)``; log a failure as callWithLogger does, with the logger's prefix."""
    try:
        return func(*args, **kw)
    except KeyboardInterrupt:
        raise
    except BaseException:
        from twisted.python import log

        try:
            prefix = logger.logPrefix()
        except Exception:
            prefix = "(buggy logPrefix method)"
        log.err(system=prefix)
        return None


def segments_without_debug_lines() -> None:
    """Hand each received segment to autobahn's parser without formatting a debug line nobody reads."""
    # autobahn's Twisted adapter builds the arguments of a log.debug call for every segment (the
    # method's qualified name through inspect, the peer, the length) before daphne's logger drops
    # them: 5 % of an idle fleet's cost in daphne, and paid again for every frame under ingest.
    module = sys.modules.get("daphne.ws_protocol")
    if module is None or getattr(module.WebSocketProtocol, "_bridgeos_quiet_segments", False):
        return

    def data_received(self: Any, data: bytes) -> None:
        self._dataReceived(data)

    module.WebSocketProtocol.dataReceived = data_received
    module.WebSocketProtocol._bridgeos_quiet_segments = True


# A client's ping: final frame, opcode 9, masked, the payload's length (control frames: <= 125).
_PING = 0x89
_PONG = 0x8A
_MASKED = 0x80


def pings_answered_directly() -> None:
    """Answer a lone ping from a robot with its pong at once, without autobahn's general frame parser."""
    # 10,000 robots send 2,000 pings a second. Each went through autobahn's frame parser, its
    # control-frame dispatch, daphne's onPing and a general frame builder: about 70 us, nearly all
    # of an idle fleet's cost in daphne (py-spy). A segment that is exactly one complete ping, on an
    # open connection with nothing buffered, gets the same pong and the same bookkeeping (the traffic
    # counters, and the ping as a sign of life); anything else goes the general way, as before.
    module = sys.modules.get("daphne.ws_protocol")
    if module is None or getattr(module.WebSocketProtocol, "_bridgeos_direct_pongs", False):
        return
    protocol = module.WebSocketProtocol
    general = protocol._dataReceived
    state_open = protocol.STATE_OPEN

    def data_received(self: Any, data: bytes) -> None:
        if (
            len(data) >= 6
            and data[0] == _PING
            and data[1] & _MASKED
            and len(data) == 6 + (data[1] & 0x7F)  # one whole ping, so at most 125 bytes of payload
            and self.state == state_open
            and not self.data
            and self.current_frame is None
            and not self.send_queue  # nothing autobahn holds back to send first
            and not self.logOctets
            and not self.logFrames
            and type(data) is bytes
        ):
            payload = unmask(data[6:], data[2:6])
            pong = bytes((_PONG, len(payload))) + payload
            self.trafficStats.incomingOctetsWireLevel += len(data)
            self.trafficStats.outgoingOctetsWireLevel += len(pong)
            self.last_ping = time.time()  # as heartbeats_count_as_traffic has it
            self.transport.write(pong)
            return
        general(self, data)

    protocol._dataReceived = data_received
    protocol._bridgeos_direct_pongs = True


# A client's text message in one frame: final, opcode 1, no extension bits; masked, 7- or 16-bit length.
_TEXT = 0x81
_LENGTH_16 = 126


def unmask(payload: bytes, mask: bytes) -> bytes:
    """Return a client frame's payload unmasked (RFC 6455 5.3): XORed with its 4-byte key, repeated."""
    size = len(payload)
    key = (mask * (size // 4 + 1))[:size]
    # One XOR of two big integers: a few microseconds for a kilobyte, in C, where a loop over bytes takes 100.
    return (int.from_bytes(payload, "little") ^ int.from_bytes(key, "little")).to_bytes(size, "little")


def text_frames_read_directly() -> None:
    """Hand a robot's lone text frame to daphne at once, without autobahn's general frame parser."""
    # A robot's report is one text frame in one segment. autobahn took it through its frame parser's
    # state machine, a frame and a message begun and ended, a cffi unmasker and UTF-8 validator, and
    # a future for the message's (absent) observers: a fifth of daphne's main thread while 10,000
    # robots sent 2,000 metrics frames a second (py-spy). A segment that is exactly one complete,
    # masked, unfragmented text frame of valid UTF-8 within the size limits, on an open connection
    # with nothing buffered or begun, gets the same bookkeeping and reaches daphne's onMessage as
    # before; anything else (a bad frame, too big, fragments, a partial segment) goes the general way.
    module = sys.modules.get("daphne.ws_protocol")
    if module is None or getattr(module.WebSocketProtocol, "_bridgeos_direct_text", False):
        return
    protocol = module.WebSocketProtocol
    general = protocol._dataReceived
    state_open = protocol.STATE_OPEN

    def data_received(self: Any, data: bytes) -> None:
        size = len(data)
        if size > 6 and data[0] == _TEXT and data[1] & _MASKED and type(data) is bytes:
            length = data[1] & 0x7F
            start = 6
            if length == _LENGTH_16:
                length = int.from_bytes(data[2:4], "big")
                start = 8
                if length < _LENGTH_16:
                    length = -1  # not the shortest encoding: autobahn fails the connection for it
            if (
                length > 0
                and size == start + length
                and self.state == state_open
                and not self.data
                and self.current_frame is None
                and not self.inside_message
                and not self.failedByMe
                and not self.logOctets
                and not self.logFrames
                and not self.trackedTimings
                and self.autoPingTimeoutCall is None
                and not self._listeners  # nobody observes "message" events
                and not 0 < self.maxMessagePayloadSize < length
                and not 0 < self.maxFramePayloadSize < length
            ):
                payload = unmask(data[start:], data[start - 4 : start])
                try:
                    payload.decode("utf-8")
                except UnicodeDecodeError:
                    general(self, data)  # autobahn fails the connection, with its own reason
                    return
                stats = self.trafficStats
                stats.incomingOctetsWireLevel += size
                stats.incomingOctetsWebSocketLevel += length
                stats.incomingOctetsAppLevel += length
                stats.incomingWebSocketFrames += 1
                stats.incomingWebSocketMessages += 1
                self._onMessage(payload, False)
                return
        general(self, data)

    protocol._dataReceived = data_received
    protocol._bridgeos_direct_text = True


class _Gathering:
    """The connections written to inside one ``gathered_writes`` block, and what each was given."""

    __slots__ = ("chunks", "open")

    def __init__(self) -> None:
        self.chunks: dict[Any, list[bytes]] = {}
        self.open = True


# Set in the task that opened the block. A timer or task started inside copies the context and
# outlives the block: ``open`` tells it the block has ended, so its writes go out as they come
# (a robot's login frames were resent into a block long gone, and reached it only with a later write).
_GATHERING: ContextVar[_Gathering | None] = ContextVar("bridgeos_gathering", default=None)


@contextmanager
def gathered_writes() -> Iterator[None]:
    """Send the frames written inside to each connection together, in one send, when the block ends."""
    # A robot's login is three frames (authentication_success, connection_established, robot_config):
    # three sends, a fifth of daphne's main thread while 10,000 robots connect (py-spy), and three
    # reads for the robot. Gathered, they are one send and one read. Only writes that would have
    # gone out at once are gathered (see write_through_when_idle); outside daphne nothing changes.
    outer = _GATHERING.get()
    if outer is not None and outer.open:
        yield  # already inside one: the outer block sends
        return
    gathering = _Gathering()
    token = _GATHERING.set(gathering)
    try:
        yield
    finally:
        gathering.open = False
        _GATHERING.reset(token)
        for connection, chunks in gathering.chunks.items():
            if chunks and connection.__dict__.get("_bridgeos_gathered") is chunks:
                connection._bridgeos_gathered = None
                connection.write(b"".join(chunks))


def write_through_when_idle() -> None:
    """Have a TCP connection with nothing queued send at once, as asyncio's transports do, not a loop turn later."""
    # Twisted queues every write and registers the socket for writability (two epoll_ctl calls and a
    # loop turn per frame through the asyncio reactor): a third of an idle fleet's cost in daphne is
    # the pongs to 2,000 heartbeats a second going that way. Anything already queued keeps its order,
    # and a producer (HTTPChannel registers one) is paused only by what is queued, as before. Inside
    # gathered_writes such writes wait for the block's end instead, and go out as one.
    tcp = sys.modules.get("twisted.internet.tcp")
    if tcp is None or getattr(tcp.Connection, "_bridgeos_write_through", False):
        return
    queued_write = tcp.Connection.write
    queued_sequence = tcp.Connection.writeSequence
    queued_close = tcp.Connection.loseConnection

    def release_gathered(connection: Any) -> None:
        """Queue what a block gathered for this connection, ahead of a write that cannot wait for the block."""
        chunks = connection.__dict__.get("_bridgeos_gathered")
        if chunks:
            connection._bridgeos_gathered = None
            data = b"".join(chunks)
            chunks.clear()
            queued_write(connection, data)

    def write(self: Any, data: bytes) -> None:
        pending = self.__dict__.get("_bridgeos_gathered")
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
            gathering = _GATHERING.get()
            if gathering is not None and gathering.open:
                if pending is None:
                    pending = self._bridgeos_gathered = gathering.chunks.setdefault(self, [])
                if gathering.chunks.get(self) is pending:
                    pending.append(data)
                    return
            elif pending is None:
                sent = self.writeSomeData(data)
                if isinstance(sent, int) and sent > 0:
                    if sent == len(data):
                        return
                    data = data[sent:]
                # Nothing sent (the socket is full) or the connection is lost: queued, and doWrite finds out.
                queued_write(self, data)
                return
        release_gathered(self)  # what another block gathered for this connection goes first
        queued_write(self, data)

    def write_sequence(self: Any, iovec: list[bytes]) -> None:
        release_gathered(self)
        queued_sequence(self, iovec)

    def lose_connection(self: Any) -> None:
        release_gathered(self)  # closing sends what is queued first
        queued_close(self)

    tcp.Connection.write = write
    tcp.Connection.writeSequence = write_sequence
    tcp.Connection.loseConnection = lose_connection
    tcp.Connection._bridgeos_write_through = True


# Allocations between young collections (CPython's default: 700), and how many collections of each
# generation trigger one of the next (defaults: 10 and 10).
GC_THRESHOLDS = (50_000, 50, 10)


def fewer_garbage_collections() -> None:
    """Collect cycles far less often, and never scan again what the server loaded before it started."""
    # A robot's frame lives from its arrival to its commit, long enough to survive young collections
    # into the old generation, and with thousands of robots connected every full collection walks
    # millions of objects: at 3,000 robots sending 600 metric frames a second, the collector took
    # half of daphne's CPU (gc callbacks), and its pauses held acks back. With these thresholds the
    # same load took 18 % of a core instead of 38 %, and 10,000 robots connected in 9.9 s, not 15.9 s.
    # Every connection leaves ~125 objects that the collector walks once young and once more in the
    # middle generation: with a middle collection every 20 young ones, two of them (0.35-0.5 s each)
    # fell inside a 10,000-robot connect storm; every 50, none does, and the walk comes after it.
    # Garbage without cycles is freed at once as ever; a closed connection's cycles wait a little longer.
    if "daphne.server" not in sys.modules:
        return
    import gc

    gc.freeze()
    gc.set_threshold(*GC_THRESHOLDS)


# How long an access-log line may wait in daphne's buffer before it is written.
ACCESS_LOG_FLUSH_S = 0.5


def buffered_access_log() -> None:
    """Write daphne's access log (its stdout) a block at a time, flushed every half second and at exit."""
    # Every server here runs with PYTHONUNBUFFERED, so each access line was a write(2) of its own:
    # two per robot connecting (WSCONNECTING, WSCONNECT), a tenth of daphne's main thread while
    # 10,000 robots connect at once (py-spy). Buffered, 2,000 lines are ~25 writes. Errors go to
    # stderr, which stays unbuffered; a kill -9 loses at most the last half second of access lines.
    reactor = sys.modules.get("twisted.internet.reactor")
    stream = sys.stdout
    if "daphne.server" not in sys.modules or reactor is None or not isinstance(stream, io.TextIOWrapper):
        return
    if not (stream.write_through or stream.line_buffering):
        return  # already buffered (tuned once, or started without PYTHONUNBUFFERED)
    from twisted.internet.task import LoopingCall

    def flush() -> None:
        try:
            stream.flush()
        except (OSError, ValueError):
            pass  # a closed or broken stdout: the lines are lost either way, and daphne must go on

    stream.reconfigure(line_buffering=False, write_through=False)
    reactor.callWhenRunning(LoopingCall(flush).start, ACCESS_LOG_FLUSH_S, now=False)
    reactor.addSystemEventTrigger("after", "shutdown", flush)


CLOSE_HANDSHAKE_TIMEOUT_S = 10.0


def patient_close_handshakes() -> None:
    """Give a peer 10 s, not autobahn's 1 s, to answer daphne's close before its connection is reset."""
    # After refusing a frame daphne closes the connection, and autobahn resets it if the peer's
    # close reply is over a second late. A client whose reply then fails may drop the refusal it had
    # already read (websockets' sync client does): a robot on a slow link, or a client thread starved
    # for a second, lost the reason it was closed. A class attribute wins over the factory's default.
    module = sys.modules.get("daphne.ws_protocol")
    if module is not None:
        module.WebSocketProtocol.closeHandshakeTimeout = CLOSE_HANDSHAKE_TIMEOUT_S


def applications_reaped_when_they_end() -> None:
    """Check the connections whose socket or application ended since the last pass, not all of them, each second."""
    # daphne's application_checker walked every connection each second to find the few that had
    # closed or whose application had returned: 3 % of an idle fleet's cost at 10,000 robots
    # (py-spy). A connection now enters the pass when either ends, and stays in it while a closed
    # connection's application has yet to stop (so the close timeout still cancels it). Each is
    # checked as daphne checks it (daphne 4.2).
    module = sys.modules.get("daphne.server")
    if module is None or getattr(module.Server, "_bridgeos_reaps_ended", False):
        return
    server_class = module.Server
    disconnected, create = server_class.protocol_disconnected, server_class.create_application

    def ended(server: Any) -> set[Any]:
        if "_bridgeos_ended" not in server.__dict__:
            server._bridgeos_ended = set()
        return server._bridgeos_ended

    def protocol_disconnected(self: Any, protocol: Any) -> None:
        disconnected(self, protocol)
        ended(self).add(protocol)

    def create_application(self: Any, protocol: Any, scope: dict[str, Any]) -> Any:
        queue = create(self, protocol, scope)
        application = self.connections.get(protocol, {}).get("application_instance")
        if application is not None:
            application.add_done_callback(lambda _: ended(self).add(protocol))
        return queue

    def application_checker(self: Any) -> None:
        walk, self._bridgeos_ended = ended(self), set()
        for protocol in walk:
            if protocol in self.connections and not reap(self, protocol, module.logger):
                self._bridgeos_ended.add(protocol)
        module.reactor.callLater(1, self.application_checker)

    server_class.protocol_disconnected = protocol_disconnected
    server_class.create_application = create_application
    server_class.application_checker = application_checker
    server_class._bridgeos_reaps_ended = True


def reap(server: Any, protocol: Any, logger: Any) -> bool:
    """Do daphne's application_checker for one connection; False while it is closed and its application runs."""
    details = server.connections[protocol]
    disconnected = details.get("disconnected")
    application = details.get("application_instance")
    if disconnected and time.time() - disconnected > server.application_close_timeout:
        if application and not application.done():
            logger.warning(
                "Application instance %r for connection %s took too long to shut down and was killed.",
                application,
                repr(protocol),
            )
            application.cancel()
    if application and application.done():
        try:
            exception = application.exception()
        except asyncio.CancelledError:
            pass
        else:
            if isinstance(exception, KeyboardInterrupt):
                server.stop()  # the protocol asks the server to exit
            elif exception:
                logger.error("Exception inside application: %s", exception, exc_info=exception)
                if not disconnected:
                    protocol.handle_exception(exception)
        del details["application_instance"]
        application = None
    if not application and disconnected:
        del server.connections[protocol]
    return not (application and disconnected)


def timeouts_checked_in_one_pass() -> None:
    """Skip, in daphne's timeout pass, the open WebSocket connections that have nothing due."""
    # daphne's timeout_checker called every connection's check_timeouts every 2 s, which at
    # 10,000 idle robots found nothing to do for almost all of them: 5 % of the fleet's cost
    # (py-spy). The pass now compares the same clocks inline and calls check_timeouts only for a
    # connection with something due (its lifetime, its ping), still connecting, or not a WebSocket.
    server_module = sys.modules.get("daphne.server")
    ws_module = sys.modules.get("daphne.ws_protocol")
    if server_module is None or ws_module is None or getattr(server_module.Server, "_bridgeos_one_pass", False):
        return
    websocket = ws_module.WebSocketProtocol

    def timeout_checker(self: Any) -> None:
        now = time.time()
        lifetime = self.websocket_timeout if self.websocket_timeout >= 0 else float("inf")
        for protocol in list(self.connections):
            if (
                type(protocol) is not websocket
                or protocol.state != websocket.STATE_OPEN
                or now - protocol.socket_opened > lifetime
                or now - protocol.last_ping > self.ping_interval
            ):
                protocol.check_timeouts()
        server_module.reactor.callLater(2, self.timeout_checker)

    server_module.Server.timeout_checker = timeout_checker
    server_module.Server._bridgeos_one_pass = True
