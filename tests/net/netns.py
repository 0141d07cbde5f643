"""Network namespaces for the VPN tests and benchmark: hosts joined by veth links, torn down whatever happens.

Every namespace and link is named ``bosnet-<tag>…`` (the tag is this process's pid in hex), so
parallel runs never collide and leftovers of a dead run are recognised and removed. A
``PortBridge`` lets processes inside a namespace reach a service on this machine's loopback
(PostgreSQL, Redis) the way a cloud host reaches its database host: a listener opened inside
the namespace, relaying to the real port.
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import re
import signal
import socket
import subprocess
import threading
import time
from collections.abc import Sequence
from pathlib import Path

PREFIX = "bosnet-"
CLONE_NEWNET = 0x40000000
_libc = ctypes.CDLL(None, use_errno=True)


def run(*args: str, check: bool = True, timeout: float = 30.0) -> subprocess.CompletedProcess:
    """Run a command, raising with its output when it fails."""
    result = subprocess.run(list(args), capture_output=True, text=True, timeout=timeout)
    if check and result.returncode != 0:
        raise RuntimeError(f"{' '.join(args)} failed ({result.returncode}): {result.stderr.strip()[:2000]}")
    return result


def available() -> str | None:
    """Return why namespaces with OpenVPN cannot be used here, or None when they can."""
    if os.geteuid() != 0:
        return "needs root (ip netns)"
    for tool in ("ip", "openvpn", "nft", "ping"):
        if subprocess.run(["which", tool], capture_output=True).returncode != 0:
            return f"{tool} is not installed (scripts/services.sh vpn)"
    if not Path("/dev/net/tun").exists():
        return "/dev/net/tun is missing"
    return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def remove_stale() -> None:
    """Delete namespaces left by runs whose process is gone."""
    listing = run("ip", "netns", "list", check=False).stdout
    for line in listing.splitlines():
        name = line.split()[0] if line.split() else ""
        match = re.fullmatch(rf"{PREFIX}([0-9a-f]+)-.*", name)
        if match and not _pid_alive(int(match.group(1), 16)):
            _kill_all(name)
            run("ip", "netns", "del", name, check=False)


def _kill_all(namespace: str) -> None:
    pids = run("ip", "netns", "pids", namespace, check=False).stdout.split()
    for pid in pids:
        with contextlib.suppress(ProcessLookupError, ValueError):
            os.kill(int(pid), signal.SIGKILL)


class Network:
    """Namespaces joined by veth links; ``close()`` kills every process in them and deletes them."""

    def __init__(self) -> None:
        remove_stale()
        self.tag = f"{os.getpid():x}"
        self.namespaces: list[str] = []
        self.links = 0
        self.bridges: list[PortBridge] = []

    def host(self, name: str, *, forward: bool = False) -> str:
        """Create a namespace with loopback up; ``forward`` makes it a router."""
        namespace = f"{PREFIX}{self.tag}-{name}"
        run("ip", "netns", "add", namespace)
        self.namespaces.append(namespace)
        self.exec(namespace, "ip", "link", "set", "lo", "up")
        if forward:
            self.exec(namespace, "sysctl", "-qw", "net.ipv4.ip_forward=1")
        return namespace

    def link(self, a: str, address_a: str, b: str, address_b: str) -> tuple[str, str]:
        """Join two namespaces with a veth pair addressed ``address_a`` and ``address_b`` (CIDR)."""
        self.links += 1
        end_a, end_b = f"{PREFIX}{self.tag}{self.links}a", f"{PREFIX}{self.tag}{self.links}b"
        if len(end_a) > 15:
            end_a, end_b = f"bn{self.tag}{self.links}a", f"bn{self.tag}{self.links}b"
        run("ip", "link", "add", end_a, "netns", a, "type", "veth", "peer", "name", end_b, "netns", b)
        for namespace, end, address in ((a, end_a, address_a), (b, end_b, address_b)):
            self.exec(namespace, "ip", "addr", "add", address, "dev", end)
            self.exec(namespace, "ip", "link", "set", end, "up")
        return end_a, end_b

    def exec(
        self, namespace: str, *args: str, check: bool = True, timeout: float = 30.0
    ) -> subprocess.CompletedProcess:
        """Run a command inside a namespace."""
        return run("ip", "netns", "exec", namespace, *args, check=check, timeout=timeout)

    def command(self, namespace: str, args: Sequence[str]) -> list[str]:
        """Return the argv that runs ``args`` inside a namespace (for Popen)."""
        return ["ip", "netns", "exec", namespace, *args]

    def bridge(self, namespace: str, port: int) -> PortBridge:
        """Make 127.0.0.1:port inside the namespace reach 127.0.0.1:port of this machine."""
        bridge = PortBridge(namespace, port)
        self.bridges.append(bridge)
        return bridge

    def close(self) -> None:
        """Kill every process in the namespaces and delete them (their links go with them)."""
        for bridge in self.bridges:
            bridge.close()
        for namespace in reversed(self.namespaces):
            _kill_all(namespace)
        deadline = time.monotonic() + 10
        for namespace in reversed(self.namespaces):
            while run("ip", "netns", "pids", namespace, check=False).stdout.split() and time.monotonic() < deadline:
                time.sleep(0.05)
            run("ip", "netns", "del", namespace, check=False)
        self.namespaces.clear()


def _in_namespace(namespace: str, make: callable) -> object:
    """Call ``make()`` on a thread that entered the namespace, so sockets it opens live there."""
    result: dict[str, object] = {}

    def work() -> None:
        fd = os.open(f"/run/netns/{namespace}", os.O_RDONLY)
        try:
            if _libc.setns(fd, CLONE_NEWNET) != 0:
                raise OSError(ctypes.get_errno(), "setns failed")
            result["value"] = make()
        except BaseException as exc:
            result["error"] = exc
        finally:
            os.close(fd)

    thread = threading.Thread(target=work)
    thread.start()
    thread.join()
    if "error" in result:
        raise result["error"]  # type: ignore[misc]
    return result["value"]


class PortBridge:
    """Relay connections to 127.0.0.1:port inside a namespace to 127.0.0.1:port here."""

    def __init__(self, namespace: str, port: int) -> None:
        self.port = port
        self.listener: socket.socket = _in_namespace(namespace, lambda: socket.create_server(("127.0.0.1", port)))  # type: ignore[assignment]
        self.sockets: set[socket.socket] = set()
        self.closed = False
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while not self.closed:
            try:
                inside, _ = self.listener.accept()
            except OSError:
                return
            try:
                outside = socket.create_connection(("127.0.0.1", self.port), timeout=10)
                outside.settimeout(None)
            except OSError:
                inside.close()
                continue
            self.sockets |= {inside, outside}
            threading.Thread(target=self._pump, args=(inside, outside), daemon=True).start()
            threading.Thread(target=self._pump, args=(outside, inside), daemon=True).start()

    def _pump(self, source: socket.socket, target: socket.socket) -> None:
        try:
            while data := source.recv(65536):
                target.sendall(data)
        except OSError:
            pass
        finally:
            with contextlib.suppress(OSError):
                target.shutdown(socket.SHUT_WR)

    def close(self) -> None:
        self.closed = True
        with contextlib.suppress(OSError):
            self.listener.close()
        for sock in list(self.sockets):
            with contextlib.suppress(OSError):
                sock.close()
