"""Keep the robot's OpenVPN tunnel to the cloud up and know, through its management socket, whether it is.

OpenVPN runs as a child process in a session of its own with a management socket in
the agent's data directory; the agent follows its state (``state on all``) and restarts it
with backoff when it exits. ``up`` is true only while OpenVPN says CONNECTED.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import signal
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

__all__ = ["VpnClient", "parse_state"]

STATE_LINE = re.compile(r"^(?:>STATE:)?(\d+),([A-Z_]+),([^,]*),([^,]*)")
MANAGEMENT_WAIT_S = 15.0


def parse_state(line: str) -> tuple[str, str | None] | None:
    """Return (state, tunnel address) from a management state line, or None for other lines."""
    match = STATE_LINE.match(line.strip())
    if match is None:
        return None
    return match.group(2), (match.group(4) or None)


class VpnClient:
    """Run OpenVPN with a client profile, restart it when it dies, and report its state."""

    def __init__(
        self,
        profile: str,
        *,
        workdir: Path,
        device: str,
        openvpn: str = "openvpn",
        on_change: Callable[[bool], None] | None = None,
        say: Callable[[str], None] = print,
        restart_initial: float = 1.0,
        restart_max: float = 30.0,
    ) -> None:
        self.workdir = Path(workdir)
        self.device = device
        self.openvpn = openvpn
        self.on_change = on_change
        self.say = say
        self.restart_initial = restart_initial
        self.restart_max = restart_max
        self.state = "DOWN"
        self.address: str | None = None
        self.up = False
        self.starts = 0
        self.process: asyncio.subprocess.Process | None = None
        self._task: asyncio.Task[None] | None = None
        self.workdir.mkdir(parents=True, exist_ok=True)
        self.profile_path = self.workdir / "client.ovpn"
        self.socket_path = self.workdir / "management.sock"
        if len(str(self.socket_path)) > 100:
            # A unix socket's path is limited to 108 bytes; a deep data directory needs a short home.
            self.socket_path = Path(tempfile.mkdtemp(prefix="bridgeos-vpn-")) / "management.sock"
        self.log_path = self.workdir / "openvpn.log"
        self.write_profile(profile)

    def write_profile(self, profile: str) -> None:
        """Keep the profile (it holds the robot's private key) readable by this user only."""
        tmp = self.profile_path.with_suffix(".tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as out:
            out.write(profile)
        os.replace(tmp, self.profile_path)

    def start(self) -> None:
        """Start supervising OpenVPN in the background."""
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._supervise(), name="vpn")

    async def close(self) -> None:
        """Stop OpenVPN and the supervision; the tunnel goes down."""
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
            self._task = None
        await self._stop_process()
        self._set("DOWN", None)

    # ------------------------------------------------------------------ internals

    def _set(self, state: str, address: str | None) -> None:
        self.state = state
        up = state == "CONNECTED"
        if up:
            self.address = address or self.address
        if up != self.up:
            self.up = up
            self.say(f"VPN tunnel {'up, address ' + str(self.address) if up else 'down (' + state.lower() + ')'}")
            if self.on_change is not None:
                self.on_change(up)

    async def _supervise(self) -> None:
        delay = self.restart_initial
        while True:
            started = time.monotonic()
            try:
                await self._run_once()
            except OSError as exc:
                self.say(f"VPN: cannot run {self.openvpn}: {exc}")
            self._set("DOWN", None)
            if time.monotonic() - started > 60:
                delay = self.restart_initial  # it ran a good while: this is a fresh failure
            await asyncio.sleep(delay)
            delay = min(self.restart_max, delay * 2)

    async def _run_once(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            self.socket_path.unlink()
        log = open(self.log_path, "ab")  # noqa: ASYNC230 - a local file, opened once per OpenVPN start
        try:
            self.process = await asyncio.create_subprocess_exec(
                self.openvpn,
                "--config",
                str(self.profile_path),
                "--dev",
                self.device,
                "--dev-type",
                "tun",
                "--management",
                str(self.socket_path),
                "unix",
                stdin=asyncio.subprocess.DEVNULL,
                stdout=log,
                stderr=asyncio.subprocess.STDOUT,
                start_new_session=True,  # our signals (Ctrl-C) are not its: we stop it ourselves
            )
        finally:
            log.close()
        self.starts += 1
        self._set("CONNECTING", None)
        try:
            await self._follow()
        finally:
            await self._stop_process()

    async def _follow(self) -> None:
        """Read state changes from the management socket until OpenVPN exits."""
        assert self.process is not None
        deadline = time.monotonic() + MANAGEMENT_WAIT_S
        reader = writer = None
        while reader is None:
            if self.process.returncode is not None:
                return
            try:
                reader, writer = await asyncio.open_unix_connection(str(self.socket_path))
            except OSError:
                if time.monotonic() > deadline:
                    self.say("VPN: OpenVPN's management socket never appeared; restarting it")
                    return
                await asyncio.sleep(0.05)
        assert writer is not None
        try:
            writer.write(b"state on all\n")
            await writer.drain()
            while line := await reader.readline():
                parsed = parse_state(line.decode(errors="replace"))
                if parsed is not None:
                    self._set(*parsed)
        finally:
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()

    async def _stop_process(self) -> None:
        process, self.process = self.process, None
        if process is None or process.returncode is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            process.send_signal(signal.SIGTERM)
        try:
            await asyncio.wait_for(process.wait(), 10)
        except TimeoutError:
            with contextlib.suppress(ProcessLookupError):
                process.kill()
            await process.wait()
