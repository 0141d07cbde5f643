"""The robot's link to the cloud: connect on the preferred path, authenticate, send reliably, receive once.

The protocol core is ``protocol``'s sans-IO classes, shared with the cloud's consumer:
``Reliable`` retransmits unacknowledged frames with jittered backoff, ``Dedup`` applies a
retransmitted command once, ``Correlator`` matches answers to requests and expires the
unanswered. This module is the thin adapter between them, the outbox and the socket.
"""

from __future__ import annotations

import asyncio
import functools
import logging
import sqlite3
import ssl
import time
from collections.abc import Awaitable, Callable, Mapping
from typing import TYPE_CHECKING, Any

import websockets
import websockets.asyncio.client
from websockets.client import backoff

from bridgeos_agent import protocol
from bridgeos_agent.logonce import LogOnce
from bridgeos_agent.network import VPN, CloudNetwork, Target
from bridgeos_agent.outbox import Outbox
from bridgeos_agent.protocol import Envelope, Event, ProtocolError
from bridgeos_agent.tasks import TaskOwner

if TYPE_CHECKING:
    from bridgeos_agent.agentsettings import AgentSettings

__all__ = ["EXIT_REFUSED", "RETRY_CODES", "AuthenticationRefused", "Reply", "Session", "ws_scheme"]

logger = logging.getLogger("bridgeos_agent")

# The agent's exit code when the cloud refuses the robot's id or token.
EXIT_REFUSED = 3
# Error codes from the cloud that mean "try again later": the frame stays owed.
RETRY_CODES = frozenset({"unavailable", "internal_error", "rate_limited"})
# A sent frame is retransmitted after 5 s, then 10, 20 and every 30 s until acked (±10% jitter).
RESEND_INITIAL = 5.0
# How long a login may wait for the cloud's answer: as long as daphne lets a WebSocket wait to be
# accepted (30 s, scripts/daphne), since in a connect storm of thousands both queue in one loop.
LOGIN_ANSWER_S = 30.0
RESEND_CAP = 30.0
# How often owed frames and unanswered requests are checked.
TICK = 0.5
# Socket errors that only mean "this connection is gone".
CLOSE_ERRORS = (OSError, TimeoutError, websockets.WebSocketException)

Reply = tuple[Event, dict[str, Any]]


class AuthenticationRefused(RuntimeError):
    """The cloud refused the robot's id or token: retrying will not help."""


class LoginUnanswered(RuntimeError):
    """The cloud did not answer the robot's login in time: the next attempt may be."""


def ws_scheme(ws: Any) -> str:
    """Name the scheme of a live connection (WSS or plain WS)."""
    return "WSS" if getattr(ws, "transport", None) and ws.transport.get_extra_info("sslcontext") else "WS"


class Session:
    """Keep one robot connected to the cloud and carry its frames both ways."""

    def __init__(
        self,
        settings: AgentSettings,
        network: CloudNetwork,
        outbox: Outbox,
        tasks: TaskOwner,
        *,
        say: Callable[[str], None],
        handle: Callable[[Envelope], Awaitable[Reply | None]],
        timing: Callable[[], tuple[float, float]],
        on_authenticated: Callable[[Any], None],
        on_contact: Callable[[], None],
        on_refused: Callable[[Envelope, str], None],
        stop: Callable[[int], None],
        stopped: asyncio.Event,
        on_disconnect: Callable[[], None] | None = None,
    ) -> None:
        self.settings = settings
        self.network = network
        self.outbox = outbox
        self.tasks = tasks
        self.say = say
        self._handle_event = handle
        self._timing = timing  # (heartbeat interval, connection lost after) from the robot config
        self._on_authenticated = on_authenticated
        self._on_contact = on_contact
        self._on_refused = on_refused
        self._stop = stop
        self._stopped = stopped
        self._on_disconnected = on_disconnect
        self.local_ros_master: str | None = None  # told to the cloud when authenticating
        self.local_ros2: dict[str, Any] | None = None  # the robot's ROS 2 graph, told to the cloud too
        self.ws: Any = None
        self.connected = asyncio.Event()
        self.cloud_bytes = [0, 0]  # received, sent on the cloud link
        self.metric_points_sent = 0
        self.metric_points_dropped = 0  # not kept (full disk, memory budget spent) and not sent (no connection)
        # Metric frames sent but not kept (full disk, memory budget spent): (text, points) until acked.
        self._unstored: dict[str, tuple[str, int]] = {}
        self.reliable = self._new_reliable()
        self._replaying = False
        self._holding = False  # moving to another path: new frames wait in the outbox
        # What an earlier agent applied (kept in the outbox's file) counts as seen: killed and
        # restarted, the agent answers a resent command again rather than applying it twice.
        applied = outbox.applied.load()
        self._dedup = protocol.Dedup(capacity=outbox.applied.kept, ids=(frame_id for frame_id, _ in applied))
        self._answers: dict[str, str] = dict(applied)  # command id -> the frame that answered it
        self._remembering = LogOnce(logger, "keeping an applied command's id on disk")
        self._handling: set[str] = set()  # ids of frames whose handler has not answered yet
        self._requests = protocol.Correlator()
        self._replies: dict[str, asyncio.Future[Envelope | None]] = {}
        self._tls_failure: str | None = None
        self._target: Target | None = None  # where the current connection attempts go
        # Frames the outbox does not keep (component logs: their ring is their store): id -> told the
        # cloud's answer (None: acked; else the error code, "disconnected" when the link dropped first).
        self._unkept: dict[str, Callable[[str | None], None]] = {}

    @property
    def unstored_in_flight(self) -> int:
        """Return how many metric frames not kept (full disk, memory budget spent) are sent and not yet acked."""
        return len(self._unstored)

    @staticmethod
    def _new_reliable() -> protocol.Reliable:
        return protocol.Reliable(initial=RESEND_INITIAL, cap=RESEND_CAP)

    # ------------------------------------------------------------------ connecting

    async def run(self) -> None:
        """Stay connected on the path the network prefers (VPN or WSS), moving when the preference changes."""
        while True:
            target = self.network.target()
            connecting = asyncio.ensure_future(self._connect(target))
            switching = asyncio.ensure_future(self.network.wait_change(target.path))
            watchdog = asyncio.ensure_future(self._vpn_watchdog(target))
            try:
                done, _ = await asyncio.wait({connecting, switching}, return_when=asyncio.FIRST_COMPLETED)
                if switching in done and target.path != VPN:
                    # The old path still works: let the cloud ack what is in flight, so nothing is applied twice.
                    await self._drain(timeout=3.0)
            finally:
                for task in (connecting, switching, watchdog):
                    task.cancel()
                await asyncio.gather(connecting, switching, watchdog, return_exceptions=True)
            if connecting in done:
                return  # refused: the controller stops

    async def _drain(self, timeout: float) -> None:
        """Hold new frames (the outbox keeps them) until every frame sent on this connection is acked."""
        self._holding = True
        deadline = time.monotonic() + timeout
        # Acks are handled by the reader task; a 20 ms poll for at most `timeout` is simplest.
        while self.ws is not None and len(self.reliable) and time.monotonic() < deadline:  # noqa: ASYNC110
            await asyncio.sleep(0.02)

    async def _vpn_watchdog(self, target: Target) -> None:
        """Fall back to WSS when the cloud does not answer through an up tunnel."""
        if target.path != VPN:
            return
        try:
            await asyncio.wait_for(self.connected.wait(), self.network.vpn_connect_timeout)
        except TimeoutError:
            self.network.vpn_unusable()

    async def _connect(self, target: Target) -> None:
        heartbeat, lost_after = self._timing()
        delays = functools.partial(
            backoff,
            initial_delay=self.settings.reconnect_initial,
            min_delay=self.settings.reconnect_initial,
            max_delay=self.settings.reconnect_max,
        )
        self._target = target
        self.say(f"connecting to {target.url} as robot {self.settings.robot} ({target.path})")
        async for ws in websockets.connect(
            target.url,
            reconnect_delays=delays,
            ping_interval=heartbeat,
            ping_timeout=lost_after,
            max_size=protocol.MAX_FRAME_BYTES * 2,
            open_timeout=10,
            compression=None,
            process_exception=self._connect_failed,
            create_connection=_Connection,
            **target.connect_options(),
        ):
            try:
                await self._serve(ws, target.path)
            except AuthenticationRefused as exc:
                self.say(f"the cloud refused this robot: {exc}. Check --robot and --token.")
                self._stop(EXIT_REFUSED)
                return
            except websockets.ConnectionClosed:
                pass
            except LoginUnanswered:
                # The cloud took the socket but not the login in time (a connect storm of thousands):
                # a new attempt after the backoff, never a session that stops trying.
                self.say(f"the cloud did not answer this robot's login within {LOGIN_ANSWER_S:g} s; retrying")
            finally:
                self._on_disconnect()
                current = asyncio.current_task()
                if self._stopped.is_set() or (current is not None and current.cancelling()):
                    # Moving to another path (or stopping): close this socket now, not at garbage collection.
                    await self.close_socket(ws)

    @staticmethod
    async def close_socket(ws: Any) -> None:
        """Close a socket within 2 s; one already broken needs no more."""
        try:
            await asyncio.wait_for(ws.close(), 2)
        except CLOSE_ERRORS as exc:
            logger.debug("closing the cloud socket: %s", exc)

    def _connect_failed(self, exc: Exception) -> Exception | None:
        """Say why a TLS handshake failed (once per reason), then let websockets retry as usual."""
        if isinstance(exc, ssl.SSLError):
            url = self._target.url if self._target is not None else self.network.master
            if isinstance(exc, ssl.SSLCertVerificationError):
                reason = (
                    f"TLS certificate of {url} not trusted by {self.network.trusted_by()}: "
                    f"certificate verify failed: {exc.verify_message}. Pass the CA that issued the cloud's "
                    "certificate with --ca (`make deploy` prints its path and fingerprint); retrying"
                )
            else:
                reason = f"TLS handshake with {url} failed: {exc.reason or exc}; retrying"
            if reason != self._tls_failure:
                # Once per reason: a robot retrying with backoff for hours must not fill its log with it.
                self._tls_failure = reason
                self.say(reason)
        return websockets.asyncio.client.process_exception(exc)

    async def _serve(self, ws: Any, path: str = "direct") -> None:
        """Authenticate on a fresh socket, send what is owed, then read the cloud's frames."""
        credentials: dict[str, Any] = {
            "robot": self.settings.robot,
            "token": self.settings.token,
            "ros_master": self.local_ros_master,
        }
        if self.local_ros2 is not None:
            credentials["ros2"] = self.local_ros2
        if self.settings.labels:
            credentials["labels"] = self.settings.labels
        await ws.send(protocol.encode(protocol.make(Event.AUTHENTICATION_ROBOT, credentials, now=time.time())))
        try:
            raw = await asyncio.wait_for(ws.recv(), LOGIN_ANSWER_S)
        except TimeoutError:
            raise LoginUnanswered from None
        answer = protocol.decode(raw, direction=protocol.Direction.CLOUD_TO_ROBOT)
        if answer.event != Event.AUTHENTICATION_SUCCESS:
            reason = getattr(protocol.parse_payload(answer), "reason", answer.event)
            raise AuthenticationRefused(reason)
        self._on_authenticated(protocol.parse_payload(answer))
        if isinstance(ws, _Connection):
            ws.on_pong = self._on_contact
        self.ws = ws
        self.network.path = path
        self.connected.set()
        self.say(f"connected to the cloud ({'through the VPN' if path == VPN else 'over ' + ws_scheme(ws)})")
        self._on_contact()
        await self._replay_backlog()
        # Which path this connection takes is a metric of its own ("vpn": 1 through the tunnel, 0 direct).
        await self.emit(Event.METRICS, {"metrics": [self.network.path_point(path)]})
        # The cloud pushes the config on connect; asking as well makes the agent not depend on it.
        await self.send(protocol.make(Event.ROBOT_CONFIG_GET, {}, now=time.time()))
        async for raw in ws:
            self.cloud_bytes[0] += len(raw)
            self._on_contact()
            try:
                envelope = protocol.decode(raw, direction=protocol.Direction.CLOUD_TO_ROBOT)
            except ProtocolError as exc:
                await self.send(protocol.error_frame(exc, now=time.time()))
                continue
            self._receive(envelope)

    def _on_disconnect(self) -> None:
        if self.ws is not None:
            self.say("disconnected from the cloud; frames are kept until it is back")
        self.ws = None
        self.network.path = None
        self._holding = False
        self.connected.clear()
        for frame_id, (text, points) in self._unstored.items():
            # In flight when the link dropped: kept in memory (within its budget) and sent again on reconnect.
            self.outbox.keep(frame_id, text, points=points)
            if not self.outbox.held(frame_id):
                self.metric_points_dropped += points
        self._unstored.clear()
        unkept, self._unkept = self._unkept, {}
        for told in unkept.values():
            told("disconnected")
        self._count_evicted()
        # Everything unacked is sent again, in order, from the outbox on the next connection.
        self.reliable = self._new_reliable()
        if self._on_disconnected is not None:
            self._on_disconnected()

    # ------------------------------------------------------------------ sending

    def _count_evicted(self) -> None:
        """Account for the metric frames the outbox dropped from memory to stay in its budget."""
        for frame_id, text, points in self.outbox.evictions():
            if self.ws is not None and frame_id in self.reliable:
                self._unstored[frame_id] = (text, points)  # sent on this link: it may still be acked
            else:
                self.metric_points_dropped += points

    async def _replay_backlog(self) -> None:
        """Send every frame still owed, oldest first, before anything new."""
        self._replaying = True
        try:
            sent: set[str] = set()
            # Frames made while the backlog is being sent wait in the outbox too: pass over it again
            # until a pass finds nothing new, or they would wait for the next connection.
            while True:
                fresh = 0
                now = time.monotonic()
                for _, frame_id, text in self.outbox.backlog():
                    if frame_id in sent:
                        continue
                    if self.ws is None:
                        return
                    # Reliable needs only the id and that the frame wants an ack; its text stays in the
                    # outbox (not decoded again here: a backlog can hold many MB of metrics). Registered
                    # before the send, so a frame dropped from memory meanwhile is known to be in flight.
                    self.reliable.send(_owed(frame_id), now)
                    await self.ws.send(text)
                    self.cloud_bytes[1] += len(text)
                    sent.add(frame_id)
                    fresh += 1
                if not fresh:
                    break
            if sent:
                self.say(f"re-sent {len(sent)} frame(s) kept while disconnected")
        finally:
            self._replaying = False

    async def resend_loop(self) -> None:
        """Retransmit frames the cloud has not acked while connected; give up on unanswered requests."""
        while True:
            await asyncio.sleep(TICK)
            now = time.monotonic()
            for request_id in self._requests.expired(now):
                future = self._replies.get(request_id)
                if future is not None and not future.done():
                    future.set_result(None)
            if self.ws is None or self._replaying:
                continue
            for envelope in self.reliable.due(now):
                text = self.outbox.frame(envelope.id)
                if text is None:
                    self.reliable.on_ack(envelope.id)  # acked (or thinned) meanwhile
                    continue
                await self.send_raw(text)

    async def emit(self, event: Event, data: Mapping[str, Any], *, reply_to: str | None = None) -> Envelope:
        """Send a frame to the cloud; one that changes state is kept on disk until acked."""
        envelope = protocol.make(event, dict(data), reply_to=reply_to, now=time.time())
        if event == Event.METRICS:
            self.metric_points_sent += len(data["metrics"])
        if event in protocol.REQUIRES_ACK:
            text = self.outbox.put(envelope)
            self._count_evicted()
            if self.outbox.disk_full and not self.outbox.held(envelope.id):
                # Metrics neither the full disk nor the memory budget could keep: sent once if the cloud
                # is there, else dropped (counted).
                if self.ws is None or self._replaying or self._holding:
                    self.metric_points_dropped += len(data["metrics"])
                    return envelope
                # Remembered until acked: if the link drops first, the outbox keeps it in memory if it can.
                self._unstored[envelope.id] = (text, len(data["metrics"]))
                await self.send_raw(text)
                return envelope
            if self.ws is not None and not self._replaying and not self._holding:
                self.reliable.send(envelope, time.monotonic())
                await self.send_raw(text)
        else:
            await self.send(envelope)
        return envelope

    def idle(self, max_buffered: int) -> bool:
        """Say whether the link is up and nothing waits to go ahead of a low-priority frame.

        Not while the outbox's backlog is replayed or the link moves, nor while the socket
        holds more than ``max_buffered`` bytes not yet sent: metrics and state go first.
        """
        ws = self.ws
        if ws is None or self._replaying or self._holding:
            return False
        transport = getattr(ws, "transport", None)
        return transport is None or transport.get_write_buffer_size() <= max_buffered

    async def send_unkept(self, frame_id: str, text: str, told: Callable[[str | None], None]) -> bool:
        """Send a frame its sender keeps (not the outbox): once, now; ``told`` hears the cloud's ack or refusal."""
        if self.ws is None:
            return False
        self._unkept[frame_id] = told
        await self.send_raw(text)
        return True

    def forget_unkept(self, frame_id: str) -> None:
        """Stop waiting for the answer to a frame its sender gave up on (it sends its content again)."""
        self._unkept.pop(frame_id, None)

    async def send(self, envelope: Envelope) -> None:
        """Send a frame once, now, if connected."""
        await self.send_raw(protocol.encode(envelope))

    async def send_raw(self, message: str | bytes) -> None:
        """Send an encoded frame (or a binary message: a bridge blob's part) once, now, if connected."""
        ws = self.ws
        if ws is None:
            return
        try:
            await ws.send(message)
            self.cloud_bytes[1] += len(message)
        except websockets.ConnectionClosed:
            pass

    async def request(self, event: Event, data: Mapping[str, Any], timeout: float = 10.0) -> Envelope | None:
        """Ask the cloud something and wait for the answer (None if it does not come in ``timeout`` s)."""
        await self.connected.wait()
        envelope = protocol.make(event, dict(data), now=time.time())
        future: asyncio.Future[Envelope | None] = asyncio.get_running_loop().create_future()
        self._replies[envelope.id] = future
        self._requests.expect(envelope.id, time.monotonic(), timeout)
        try:
            await self.send(envelope)
            return await future
        finally:
            self._replies.pop(envelope.id, None)

    def resolve(self, envelope: Envelope) -> bool:
        """Hand an answer to the request waiting for it; return whether one was."""
        if not self._requests.resolve(envelope):
            return False
        future = self._replies.get(envelope.reply_to or "")
        if future is not None and not future.done():
            future.set_result(envelope)
        return True

    # ------------------------------------------------------------------ receiving

    def _receive(self, envelope: Envelope) -> None:
        event = envelope.event
        if envelope.reply_to and envelope.reply_to in self._unkept and event in (Event.ACK, Event.ERROR_MESSAGE):
            code = None if event == Event.ACK else str(getattr(protocol.parse_payload(envelope), "code", "refused"))
            self._unkept.pop(envelope.reply_to)(code)
            return
        if event == Event.ACK:
            if envelope.reply_to:
                self._unstored.pop(envelope.reply_to, None)
                self.outbox.ack(envelope.reply_to)
                self.reliable.on_ack(envelope.reply_to)
            return
        if event == Event.ERROR_MESSAGE and envelope.reply_to:
            self._refused(envelope)
            return
        if event in protocol.REQUIRES_ACK and self._dedup.seen(envelope.id):
            if envelope.id in self._handling:
                return  # still being handled (a migration takes seconds): its answer comes when done
            # A retransmission of something already handled: answer it the same way again.
            answer = self._answers.get(envelope.id) or protocol.ack_text(envelope.id, now=time.time())
            self.tasks.spawn(self.send_raw(answer))
            return
        self.tasks.spawn(self._handle(envelope))

    def _refused(self, envelope: Envelope) -> None:
        """Drop a frame the cloud refused for good (a retryable refusal keeps it owed)."""
        payload = protocol.parse_payload(envelope)
        frame_id = envelope.reply_to or ""
        unstored = self._unstored.pop(frame_id, None)
        if getattr(payload, "code", None) in RETRY_CODES:
            if unstored is not None:
                # Not on disk: held in memory (within its budget) and retransmitted like the frames that are.
                unsent, points = unstored
                self.outbox.keep(frame_id, unsent, points=points)
                self._count_evicted()
                if self.outbox.held(frame_id):
                    self.reliable.send(_owed(frame_id), time.monotonic())
                else:
                    self.metric_points_dropped += points  # refused for now, and no room to keep it
            return  # kept: retransmitted later
        text = self.outbox.frame(frame_id)
        self.outbox.ack(frame_id)
        self.reliable.on_ack(frame_id)
        message = str(getattr(payload, "message", ""))
        self.say(f"the cloud refused a frame: {message}")
        if text is not None:
            self._on_refused(protocol.decode(text), message)

    async def _handle(self, envelope: Envelope) -> None:
        self._handling.add(envelope.id)
        try:
            await self._handle_once(envelope)
        finally:
            self._handling.discard(envelope.id)

    async def _handle_once(self, envelope: Envelope) -> None:
        now = time.time()
        try:
            reply = await self._handle_event(envelope)
        except ProtocolError as exc:
            await self._answer(envelope, protocol.encode(protocol.error_frame(exc, envelope.id, now=now)))
            return
        except Exception as exc:
            # Not silent: logged with its traceback, and the cloud hears the command failed.
            logger.exception("handling %s failed", envelope.event)
            error = ProtocolError(str(exc) or type(exc).__name__, code="internal_error")
            await self._answer(envelope, protocol.encode(protocol.error_frame(error, envelope.id, now=time.time())))
            return
        if reply is not None:
            event, data = reply
            await self._answer(
                envelope, protocol.encode(protocol.make(event, data, reply_to=envelope.id, now=time.time()))
            )
        elif envelope.event in protocol.REQUIRES_ACK:
            await self._answer(envelope, protocol.ack_text(envelope.id, now=time.time()))

    async def _answer(self, envelope: Envelope, text: str) -> None:
        if envelope.event in protocol.REQUIRES_ACK:
            self._answers[envelope.id] = text
            if len(self._answers) > self.outbox.applied.kept:
                self._answers.pop(next(iter(self._answers)))
            try:
                self.outbox.applied.add(envelope.id, text)
            except sqlite3.Error as exc:
                # A full or read-only disk must not hold back the answer: only a restart forgets this id.
                self._remembering.failed(exc)
            else:
                self._remembering.worked()
        await self.send_raw(text)


class _Connection(websockets.asyncio.client.ClientConnection):
    """A client connection that tells when the cloud answers a keepalive ping: a sign of life."""

    on_pong: Callable[[], None] | None = None

    def acknowledge_pings(self, data: bytes) -> None:
        super().acknowledge_pings(data)
        if self.on_pong is not None:
            self.on_pong()


def _owed(frame_id: str) -> Envelope:
    """Stand for an outbox frame in ``Reliable``: its id, and an event that wants an ack."""
    return Envelope.model_construct(event=Event.COMPONENT_STATUS.value, id=frame_id, reply_to=None, data={}, ts=0.0)
