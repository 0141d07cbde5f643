"""Drive the real @foxglove/ws-protocol client (Node, tests/js/foxglove/client.js) from a test."""

from __future__ import annotations

import json
import queue
import shutil
import subprocess
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

CLIENT_DIR = Path(__file__).parents[1] / "js" / "foxglove"


def node_client_ready() -> bool:
    return shutil.which("node") is not None and (CLIENT_DIR / "node_modules" / "@foxglove" / "ws-protocol").is_dir()


class FoxgloveClient:
    """The @foxglove/ws-protocol client in a Node process: commands in, the server's messages out."""

    def __init__(self, address: int | str, subprotocol: str = "foxglove.websocket.v1") -> None:
        """Connect to a port on this machine or to a ws:// URL (the cloud's, a ticket in its query)."""
        url = address if isinstance(address, str) else f"ws://127.0.0.1:{address}"
        self.process = subprocess.Popen(
            ["node", str(CLIENT_DIR / "client.js"), url, subprotocol],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        self.events: queue.Queue[dict[str, Any]] = queue.Queue()
        self.seen: list[dict[str, Any]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            try:
                self.events.put(json.loads(line))
            except ValueError:
                self.events.put({"event": "output", "line": line})

    def command(self, cmd: str, **fields: Any) -> None:
        assert self.process.stdin is not None
        self.process.stdin.write(json.dumps({"cmd": cmd, **fields}) + "\n")
        self.process.stdin.flush()

    def wait(
        self, event: str, match: Callable[[dict[str, Any]], bool] = lambda e: True, timeout: float = 15
    ) -> dict[str, Any]:
        """Return the first event of a kind (matching ``match``), seen before or arriving within ``timeout``."""
        for seen in self.seen:
            if seen["event"] == event and match(seen):
                self.seen.remove(seen)
                return seen
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            try:
                got = self.events.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                break
            if got["event"] == event and match(got):
                return got
            self.seen.append(got)
        kinds = sorted({e["event"] for e in self.seen})
        raise AssertionError(f"no {event} event within {timeout} s (seen: {kinds}; last: {self.seen[-3:]})")

    def channel(self, topic: str, timeout: float = 15) -> dict[str, Any]:
        """Return the advertised channel of a topic."""
        advertise = self.wait("advertise", lambda e: any(c["topic"] == topic for c in e["channels"]), timeout)
        self.seen.insert(0, advertise)  # other topics of the same advertisement stay findable
        return next(c for c in advertise["channels"] if c["topic"] == topic)

    def service(self, name: str) -> dict[str, Any]:
        """Return the advertised service of a name."""
        found = self.wait("advertiseServices", lambda e: any(s["name"] == name for s in e["services"]))
        self.seen.insert(0, found)
        return next(s for s in found["services"] if s["name"] == name)

    def status(self, says: str) -> dict[str, Any]:
        return self.wait("status", lambda e: says in e["status"]["message"])["status"]

    def close(self) -> None:
        if self.process.poll() is None:
            assert self.process.stdin is not None
            self.process.stdin.close()
            try:
                self.process.wait(5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5)
