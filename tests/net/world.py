"""A cloud and robots as network namespaces, with the real daphne (TLS), OpenVPN server and agents.

    cloud (bosnet-…-cloud): daphne on wss://192.0.2.1:8443, `manage.py vpn run` (OpenVPN + firewall),
        one veth per robot's cloud subnet to a "cloud container" namespace (…-cN), like Docker bridges
    robot N (bosnet-…-rN): the agent (or a bare OpenVPN client), a veth to its "local container"
        namespace (…-lN) on its local subnet, and a point-to-point link to the cloud

PostgreSQL and Redis stay on this machine; a PortBridge makes them answer on the cloud
namespace's loopback, as a database host would.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import socket
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tests.conftest import BIN, ROOT, service_env
from tests.logguard import watch
from tests.net.netns import Network, _in_namespace

PUBLIC = "192.0.2.1"  # the cloud's public address (TEST-NET-1, only ever inside these namespaces)
TLS_PORT = 8443
VPN_PORT = 1194
DEVICE = "bosnet-tun"


def network_settings(base: dict[str, Any]) -> dict[str, Any]:
    """Return the network settings the test cloud runs with (the test process must agree)."""
    return {
        **base,
        "VPN_REMOTES": [f"{PUBLIC}:{VPN_PORT}"],
        "VPN_DEVICE": DEVICE,
        "VPN_MASTER": f"wss://{base['VPN_SERVER_IP']}:{TLS_PORT}",
        "TLS_NAMES": [PUBLIC, "localhost"],
        "PIN_CA": True,
    }


def cloud_env(db_name: str) -> dict[str, str]:
    """Return the environment of the cloud's processes, matching network_settings()."""
    return {
        **service_env(db_name),
        "VIRTUAL_ENV": str(BIN.parent),
        "BRIDGEOS_VPN_REMOTE": f"{PUBLIC}:{VPN_PORT}",
        "BRIDGEOS_VPN_DEVICE": DEVICE,
        "BRIDGEOS_TLS_PORT": str(TLS_PORT),
        "BRIDGEOS_TLS_NAMES": f"{PUBLIC},localhost",
        "BRIDGEOS_PIN_CA": "1",
        "ALLOWED_HOSTS": f"{PUBLIC},10.8.0.1,127.0.0.1,localhost",
    }


def connects(namespace: str, host: str, port: int, timeout: float = 2.0) -> bool:
    """Tell whether a TCP connection from inside a namespace to host:port succeeds (and is answered)."""

    def attempt() -> bool:
        try:
            with socket.create_connection((host, port), timeout=timeout) as sock:
                sock.settimeout(timeout)
                return sock.recv(16) == b"bridgeos\n"
        except OSError:
            return False

    return bool(_in_namespace(namespace, attempt))


CURRENT: list[World] = []  # the world under test, whose logs a timeout prints


def wait_until(check: Any, what: str, timeout: float = 60.0, interval: float = 0.2) -> Any:
    """Poll until check() is truthy; on timeout, say what and show the world's logs."""
    deadline = time.monotonic() + timeout
    while True:
        value = check()
        if value:
            return value
        if time.monotonic() > deadline:
            logs = CURRENT[-1].diagnostics() if CURRENT else ""
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}\n{logs}")
        time.sleep(interval)


@dataclass
class RobotHost:
    """One robot's namespaces and addresses."""

    robot: str
    token: str
    ns: str
    local_ns: str
    cloud_ns: str
    local: ipaddress.IPv4Network
    cloud: ipaddress.IPv4Network
    link: str  # the robot's address on its link to the cloud
    processes: list[subprocess.Popen] = field(default_factory=list)

    @property
    def local_host(self) -> str:
        return str(self.local.network_address + 2)

    @property
    def cloud_host(self) -> str:
        return str(self.cloud.network_address + 2)


class World:
    """The cloud and its robots; close() kills every process and deletes every namespace."""

    def __init__(self, db_name: str) -> None:
        self.net = Network()
        self.db_name = db_name
        self.dir = Path(tempfile.mkdtemp(prefix=f"bosnet-{self.net.tag}-"))
        self.processes: list[subprocess.Popen] = []
        self.listeners: list[socket.socket] = []
        self.robots: dict[str, RobotHost] = {}
        self.cloud = self.net.host("cloud", forward=True)
        # On loopback: this kernel may lack the dummy device, and a /32 there is reachable on every link.
        self.net.exec(self.cloud, "ip", "addr", "add", f"{PUBLIC}/32", "dev", "lo")
        for port in (5432, 6379):
            self.net.bridge(self.cloud, port)
        self.env = cloud_env(db_name)
        CURRENT.append(self)

    def diagnostics(self) -> str:
        """Return the tail of every log of this world."""
        parts = []
        for path in sorted(self.dir.rglob("*.log")):
            parts.append(f"--- {path.relative_to(self.dir)}\n{path.read_text(errors='replace')[-2500:]}")
        return "\n".join(parts)

    # ------------------------------------------------------------------ hosts

    def add_robot(self, robot: str, token: str, local: str, cloud: str) -> RobotHost:
        """Give a robot its namespace, a local container and a cloud container on its subnets."""
        n = len(self.robots) + 1
        host = RobotHost(
            robot,
            token,
            self.net.host(f"r{n}", forward=True),
            self.net.host(f"l{n}"),
            self.net.host(f"c{n}"),
            ipaddress.ip_network(local),
            ipaddress.ip_network(cloud),
            f"10.255.{n}.2",
        )
        self.net.link(self.cloud, f"10.255.{n}.1/30", host.ns, f"{host.link}/30")
        self.net.exec(host.ns, "ip", "route", "add", f"{PUBLIC}/32", "via", f"10.255.{n}.1")
        gateway = str(host.local.network_address + 1)
        self.net.link(
            host.ns, f"{gateway}/{host.local.prefixlen}", host.local_ns, f"{host.local_host}/{host.local.prefixlen}"
        )
        self.net.exec(host.local_ns, "ip", "route", "add", "default", "via", gateway)
        gateway = str(host.cloud.network_address + 1)
        self.net.link(
            self.cloud, f"{gateway}/{host.cloud.prefixlen}", host.cloud_ns, f"{host.cloud_host}/{host.cloud.prefixlen}"
        )
        self.net.exec(host.cloud_ns, "ip", "route", "add", "default", "via", gateway)
        for namespace, address in ((host.local_ns, host.local_host), (host.cloud_ns, host.cloud_host)):
            self._serve(namespace, address)
        self.robots[robot] = host
        return host

    def _serve(self, namespace: str, address: str, port: int = 7000) -> None:
        """Answer every TCP connection to address:port inside a namespace with a greeting."""
        listener: socket.socket = _in_namespace(namespace, lambda: socket.create_server((address, port)))  # type: ignore[assignment]
        self.listeners.append(listener)

        def serve() -> None:
            while True:
                try:
                    conn, _ = listener.accept()
                except OSError:
                    return
                with contextlib.suppress(OSError), conn:
                    conn.sendall(b"bridgeos\n")

        threading.Thread(target=serve, daemon=True).start()

    # ------------------------------------------------------------------ processes

    def spawn(self, namespace: str, args: list[str], log: str, env: dict[str, str] | None = None) -> subprocess.Popen:
        """Start a process inside a namespace, logging to the world's directory."""
        with watch(self.dir / log).open("ab") as out:
            process = subprocess.Popen(
                self.net.command(namespace, args),
                cwd=ROOT,
                env=env or self.env,
                stdout=out,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        self.processes.append(process)
        return process

    def log(self, name: str) -> str:
        path = self.dir / name
        return path.read_text(errors="replace") if path.exists() else ""

    def start_cloud(self) -> None:
        """Write the TLS certificate, start daphne (HTTPS/WSS) and the VPN server with its firewall."""
        from django.core.management import call_command

        call_command("vpn", "tls", str(self.dir / "tls"), stdout=open(os.devnull, "w"))
        env = {
            **self.env,
            "BRIDGEOS_TLS_CERT": str(self.dir / "tls" / "tls.crt"),
            "BRIDGEOS_TLS_KEY": str(self.dir / "tls" / "tls.key"),
        }
        self.daphne = self.spawn(
            self.cloud, [str(ROOT / "scripts" / "daphne"), "-b", "127.0.0.1", "-p", "8000"], "daphne.log", env
        )
        self.start_vpn()
        wait_until(lambda: self._listening(TLS_PORT) or self._died(self.daphne, "daphne.log"), "daphne's TLS port")

    def start_vpn(self) -> None:
        """Start `manage.py vpn run` (OpenVPN and the firewall, kept in step with the database)."""
        self.vpn = self.spawn(
            self.cloud,
            [str(BIN / "python"), "manage.py", "vpn", "run", str(self.dir / "vpn"), "--interval", "0.5", "--firewall"],
            "vpn.log",
        )
        wait_until(
            lambda: (
                "Initialization Sequence Completed" in self.log("vpn/openvpn.log") or self._died(self.vpn, "vpn.log")
            ),
            "the OpenVPN server",
        )

    def stop_vpn(self) -> None:
        """Stop the VPN server as an operator would (SIGTERM): OpenVPN tells its clients to go."""
        self.vpn.terminate()
        self.vpn.wait(30)

    def _died(self, process: subprocess.Popen, log: str) -> bool:
        if process.poll() is not None:
            raise AssertionError(f"{log} exited with {process.returncode}:\n{self.log(log)[-3000:]}")
        return False

    def _listening(self, port: int) -> bool:
        def attempt() -> bool:
            try:
                socket.create_connection((PUBLIC, port), timeout=1).close()
                return True
            except OSError:
                return False

        return bool(_in_namespace(self.cloud, attempt))

    def agent(self, host: RobotHost, *extra: str, module: str = "bridgeos_agent.cli") -> subprocess.Popen:
        """Run the agent (or a module with the same options) on a robot, through TLS verified with the cloud CA."""
        data = self.dir / f"agent-{host.robot}"
        args = [
            str(BIN / "python"),
            "-m",
            module,
            "run",
            "--master",
            f"wss://{PUBLIC}:{TLS_PORT}",
            "--robot",
            host.robot,
            "--token",
            host.token,
            "--ca",
            str(self.dir / "tls" / "ca.crt"),
            "--vpn-device",
            DEVICE,
            "--data-dir",
            str(data),
            "--simulate",
            "--stop-components-on-exit",
            *extra,
        ]
        env = {k: v for k, v in self.env.items() if not k.startswith("BRIDGEOS_")}
        process = self.spawn(host.ns, args, f"agent-{host.robot}.log", {**env, "PYTHONUNBUFFERED": "1"})
        host.processes.append(process)
        return process

    def close(self) -> None:
        if self in CURRENT:
            CURRENT.remove(self)
        for process in reversed(self.processes):
            if process.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, 15)
        deadline = time.monotonic() + 15
        for process in self.processes:
            with contextlib.suppress(subprocess.TimeoutExpired):
                process.wait(max(0.1, deadline - time.monotonic()))
            if process.poll() is None:
                with contextlib.suppress(ProcessLookupError):
                    os.killpg(process.pid, 9)
                process.wait(5)
        for listener in self.listeners:
            with contextlib.suppress(OSError):
                listener.close()
        self.net.close()
