"""The robot's way to the cloud (thesis §3.5): through the VPN tunnel when it is up, else over WSS.

``CloudNetwork`` follows the robot config: when ``vpn.enabled`` it fetches the robot's
OpenVPN profile from the cloud (``GET /api/robot/<id>/vpn`` with the robot's token, over
the verified public path), keeps the tunnel up (``vpn.VpnClient``), applies the robot's
firewall rules (``firewall.robot_rules``), and tells the controller which URL to use. The
controller reconnects whenever the preferred path changes; the outbox keeps every frame
meanwhile, so switching loses nothing.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import ssl
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from bridgeos_agent import firewall, tls
from bridgeos_agent.robotconfig import RobotConfig
from bridgeos_agent.vpn import VpnClient

__all__ = ["DIRECT", "VPN", "CloudNetwork", "Target"]

VPN = "vpn"
DIRECT = "direct"
PROFILE_RETRY_MAX_S = 60.0


@dataclass(frozen=True)
class Target:
    """Where the next connection goes and how."""

    url: str
    path: str  # vpn | direct
    ssl: ssl.SSLContext | None

    def connect_options(self) -> dict[str, Any]:
        """Return websockets.connect's TLS option for this URL."""
        return {"ssl": self.ssl} if self.url.startswith("wss://") else {}


class CloudNetwork:
    """Choose the path to the cloud and keep the tunnel and the firewall in step with the robot config."""

    def __init__(
        self,
        *,
        master: str,
        robot: str,
        token: str,
        data_dir: Path,
        say: Callable[[str], None],
        ca_file: Path | None = None,
        allow_insecure: bool = False,
        vpn_device: str = "bridgeos-vpn",
        openvpn: str = "openvpn",
        firewall_mode: str = "auto",
        vpn_connect_timeout: float = 20.0,
        vpn_suspend_s: float = 60.0,
    ) -> None:
        self.master = master.rstrip("/")
        self.robot = robot
        self.token = token
        self.data_dir = Path(data_dir)
        self.say = say
        self.ca_file = ca_file
        self.allow_insecure = allow_insecure
        self.vpn_device = vpn_device
        self.openvpn = openvpn
        self.firewall_mode = firewall_mode
        self.vpn_connect_timeout = vpn_connect_timeout
        self.vpn_suspend_s = vpn_suspend_s
        self.config: RobotConfig | None = None
        self.vpn: VpnClient | None = None
        self._bringing_up: asyncio.Task[None] | None = None
        self._changed = asyncio.Event()
        self._suspended_until = 0.0
        self._ca_pem: str | None = None
        self._context: ssl.SSLContext | None = None
        self._firewall_shown: str | None = None
        self.path: str | None = None  # the path of the live connection, if any
        tls.check_master_url(self.master, allow_insecure=allow_insecure)

    # ------------------------------------------------------------------ choosing a path

    def ssl_context(self) -> ssl.SSLContext:
        """Return the context verifying the cloud: --ca, else the pinned CA, else the system's."""
        if self._context is None:
            self._context = tls.client_context(ca_file=self.ca_file, ca_pem=None if self.ca_file else self._ca_pem)
        return self._context

    def trusted_by(self) -> str:
        """Name what verifies the cloud's certificate, for a robot owner reading why it was refused."""
        if self.ca_file:
            return f"--ca {self.ca_file}"
        return "the CA the cloud pinned in this robot's config" if self._ca_pem else "the system's CAs (no --ca)"

    def preferred(self) -> str:
        """Return the path connections should take now."""
        if self.vpn is not None and self.vpn.up and self._vpn_master() and time.monotonic() >= self._suspended_until:
            return VPN
        return DIRECT

    def target(self) -> Target:
        """Return where to connect now."""
        path = self.preferred()
        base = self._vpn_master() if path == VPN else self.master
        assert base is not None
        return Target(base.rstrip("/") + "/ws/robot/", path, self.ssl_context())

    async def wait_change(self, path: str) -> None:
        """Return once the preferred path is no longer ``path``."""
        while self.preferred() == path:
            self._changed.clear()
            timeout = None
            if self._suspended_until > time.monotonic():
                timeout = self._suspended_until - time.monotonic()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._changed.wait(), timeout)

    def vpn_unusable(self) -> None:
        """The tunnel is up but the cloud does not answer through it: use WSS for a while."""
        self.say(f"the cloud does not answer through the VPN; using WSS for {self.vpn_suspend_s:g} s")
        self._suspended_until = time.monotonic() + self.vpn_suspend_s
        self._changed.set()

    def path_point(self, path: str) -> dict[str, Any]:
        """Return the metric point that tells the cloud which path this connection takes."""
        return {"name": "vpn", "value": 1.0 if path == VPN else 0.0, "ts": time.time(), "labels": {"path": path}}

    def _vpn_master(self) -> str | None:
        config = self.config
        if config is None or not config.vpn.enabled or not config.vpn.master:
            return None
        try:
            tls.check_master_url(config.vpn.master, allow_insecure=self.allow_insecure)
        except tls.InsecureMaster:
            return None
        return config.vpn.master

    # ------------------------------------------------------------------ following the robot config

    def apply_config(self, config: RobotConfig) -> None:
        """Bring the tunnel up or down and refresh the firewall for a new robot config."""
        old = self.config
        self.config = config
        if config.tls_ca != self._ca_pem:
            self._ca_pem = config.tls_ca
            self._context = None  # the next connection verifies with the CA the cloud pinned
        wanted = config.vpn.enabled and config.vpn.master is not None and config.subnets is not None
        if config.vpn.master and not self._vpn_master():
            self.say(f"VPN: {config.vpn.master} is not encrypted; the tunnel path needs wss:// or --allow-insecure")
        if wanted and (old is None or old.subnets != config.subnets or self.vpn is None):
            self._start_tunnel()
        elif not wanted and (self.vpn is not None or self._bringing_up is not None):
            asyncio.get_running_loop().create_task(self._stop_tunnel())
        if wanted:
            self._apply_firewall(config)
        self._changed.set()

    def _start_tunnel(self) -> None:
        if self._bringing_up is not None and not self._bringing_up.done():
            return
        self._bringing_up = asyncio.get_running_loop().create_task(self._bring_up(), name="vpn-profile")

    async def _bring_up(self) -> None:
        """Fetch this robot's profile from the cloud (retrying) and start the tunnel with it."""
        delay = 1.0
        while True:
            try:
                profile = await self._fetch_profile()
                break
            except PermissionError as exc:
                self.say(f"VPN: the cloud refused this robot's profile ({exc}); staying on WSS")
                return
            except Exception as exc:
                self.say(f"VPN: cannot fetch this robot's profile yet ({exc}); retrying in {delay:g} s")
                await asyncio.sleep(delay)
                delay = min(PROFILE_RETRY_MAX_S, delay * 2)
        if self.vpn is not None:
            await self.vpn.close()
        self.vpn = VpnClient(
            profile,
            workdir=self.data_dir / "vpn",
            device=self.vpn_device,
            openvpn=self.openvpn,
            on_change=lambda up: self._changed.set(),
            say=self.say,
        )
        self.vpn.start()
        self.say("VPN: profile received, starting the tunnel")

    async def _fetch_profile(self) -> str:
        import aiohttp

        url = f"{tls.http_base(self.master)}/api/robot/{self.robot}/vpn"
        options: dict[str, Any] = {"ssl": self.ssl_context()} if url.startswith("https://") else {}
        timeout = aiohttp.ClientTimeout(total=20)
        async with (
            aiohttp.ClientSession(timeout=timeout) as session,
            session.get(url, headers={"Authorization": f"Token {self.token}"}, **options) as response,
        ):
            text = await response.text()
            if response.status in (401, 403, 404):
                raise PermissionError(f"HTTP {response.status}")
            if response.status != 200:
                raise RuntimeError(f"HTTP {response.status}: {text[:200]}")
            return text

    async def _stop_tunnel(self) -> None:
        if self._bringing_up is not None:
            self._bringing_up.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._bringing_up
            self._bringing_up = None
        if self.vpn is not None:
            vpn, self.vpn = self.vpn, None
            await vpn.close()
            self.say("VPN: tunnel closed")
        self._changed.set()

    def _apply_firewall(self, config: RobotConfig) -> None:
        """Load the robot's rules when root (or print them for review), once per change."""
        if self.firewall_mode == "off" or config.subnets is None or not config.vpn.master:
            return
        host = urlsplit(config.vpn.master).hostname or ""
        try:
            server = str(ipaddress.ip_address(host))
        except ValueError:
            self.say(f"firewall: the cloud's VPN address {host!r} is a name, not an address; rules not generated")
            return
        port = urlsplit(config.vpn.master).port or (443 if config.vpn.master.startswith("wss") else 80)
        rules = firewall.robot_rules(
            firewall.RobotNetwork(self.robot, config.subnets.local, config.subnets.cloud),
            device=self.vpn_device,
            server=server,
            service_ports=[port],
        )
        if rules == self._firewall_shown:
            return
        self._firewall_shown = rules
        path = self.data_dir / "firewall.nft"
        path.write_text(rules)
        if self.firewall_mode == "print" or (self.firewall_mode == "auto" and not firewall.can_apply()):
            self.say(f"firewall: not root, rules not applied; review them in {path} and load them with `nft -f {path}`")
            return
        try:
            firewall.apply_rules(rules)
        except firewall.FirewallError as exc:
            self.say(f"firewall: {exc}")
            return
        self.say(f"firewall: robot rules applied (nft table inet {firewall.TABLE}, copy in {path})")

    async def close(self) -> None:
        """Bring the tunnel down."""
        await self._stop_tunnel()
