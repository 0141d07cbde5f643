"""The live side: /ws/client/ with the login's API token, for `logs -f` and `events -f`."""

from __future__ import annotations

import itertools
import json
import os
import time
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from .config import Login
from .errors import API_ERROR, AUTH, CONNECTION, NOT_FOUND, CliError

if TYPE_CHECKING:
    from websockets.sync.client import ClientConnection

OPEN_TIMEOUT_S = 15.0
REPLY_TIMEOUT_S = 15.0
_ids = itertools.count(1)
_prefix = os.urandom(4).hex()


def ws_url(base: str) -> str:
    """Return the cloud's /ws/client/ URL from its HTTP base URL."""
    scheme, rest = base.split("://", 1)
    return f"{'wss' if scheme == 'https' else 'ws'}://{rest}/ws/client/"


def frame(event: str, data: dict[str, Any]) -> tuple[str, str]:
    """Return a new frame's id and its JSON envelope."""
    frame_id = f"cli-{_prefix}-{next(_ids)}"
    envelope = {"event": event, "id": frame_id, "reply_to": None, "data": data, "ts": time.time()}
    return frame_id, json.dumps(envelope, separators=(",", ":"))


def refusal(data: dict[str, Any]) -> CliError:
    """Turn an error_message into a CliError worded as the cloud words it, with the field it names."""
    where = f" ({data['field']})" if data.get("field") else ""
    code = NOT_FOUND if data.get("code") == "not_found" else API_ERROR
    return CliError(f"{data.get('message', 'refused')}{where}", code)


class LiveClient:
    """One authenticated /ws/client/ connection: send requests, then read the frames the cloud pushes."""

    def __init__(self, login: Login) -> None:
        self.login = login
        self.socket: ClientConnection | None = None
        self.early: list[dict[str, Any]] = []  # frames read while waiting for a reply, handed out first

    def __enter__(self) -> LiveClient:
        from websockets.exceptions import InvalidHandshake, InvalidURI
        from websockets.sync.client import connect

        url = ws_url(self.login.url)
        try:
            self.socket = connect(url, open_timeout=OPEN_TIMEOUT_S, max_size=2**24, close_timeout=1)
        except (OSError, TimeoutError, InvalidHandshake, InvalidURI) as exc:
            raise CliError(f"Cannot open {url}: {exc}", CONNECTION) from None
        reply = self.request("authentication_client", {"token": self.login.token})
        if reply["event"] != "authentication_success":
            reason = reply["data"].get("reason") or reply["data"].get("message") or "refused"
            raise CliError(f"The cloud refused the token: {reason}. Run `bridgeos login` again.", AUTH)
        return self

    def __exit__(self, *exc: object) -> None:
        if self.socket is not None:
            self.socket.close()

    def receive(self, timeout: float | None = None) -> dict[str, Any]:
        """Return the next frame from the cloud; a closed connection is exit code 5."""
        from websockets.exceptions import ConnectionClosed

        assert self.socket is not None
        try:
            text = self.socket.recv(timeout=timeout)
        except ConnectionClosed as exc:
            reason = f" ({exc.rcvd.code} {exc.rcvd.reason})" if exc.rcvd else ""
            raise CliError(f"The cloud closed the live connection{reason}.", CONNECTION) from None
        envelope: dict[str, Any] = json.loads(text)
        return envelope

    def request(self, event: str, data: dict[str, Any]) -> dict[str, Any]:
        """Send a request and return the frame answering it (by its reply_to); a refusal raises a CliError."""
        assert self.socket is not None
        frame_id, text = frame(event, data)
        self.socket.send(text)
        deadline = time.monotonic() + REPLY_TIMEOUT_S
        while (left := deadline - time.monotonic()) > 0:
            try:
                envelope = self.receive(timeout=left)
            except TimeoutError:
                break
            # A refused authentication may come without reply_to (a timeout, a closed session).
            if envelope.get("reply_to") == frame_id or envelope["event"] == "authentication_failure":
                if envelope["event"] == "error_message":
                    raise refusal(envelope["data"])
                if envelope["event"] == "component_logs":
                    self.early.append(envelope)  # the answer to a subscription carries lines too
                return envelope
            self.early.append(envelope)
        raise CliError(f"The cloud did not answer {event} within {REPLY_TIMEOUT_S:g} s.", CONNECTION)

    def frames(self) -> Iterator[dict[str, Any]]:
        """Yield every frame the cloud sends, those read early first."""
        while self.early:
            yield self.early.pop(0)
        while True:
            yield self.receive()
