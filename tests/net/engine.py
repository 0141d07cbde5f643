"""A second Docker engine inside a network namespace: a robot's own engine, or a Swarm worker node.

It shares nothing with this machine's engine but the kernel: its own data root (so it starts
with an empty image store), exec root, socket, pid file, configuration file, containerd and
cgroup parent. It reaches the network only through its namespace, so what it pulls crosses
that namespace's link, where a test can shape, cut and count it. Everything is named after
the owning process's pid (``bose-<pid hex>-NAME``), so leftovers of a killed run are found and
removed by the next one.

Registries' CA certificates go to ``/etc/docker/certs.d/HOST:PORT/ca.crt``, which every engine
on the machine reads (dockerd has no flag for another directory): :meth:`Engine.trust` writes
one and :meth:`Engine.close` removes what it wrote.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import signal
import subprocess
import time
from pathlib import Path

from tests.net.netns import PortBridge, _pid_alive, run

PREFIX = "bose-"
DATA = Path("/var/lib/bridgeos-engines")
EXEC = Path("/run/bridgeos-engines")
CERTS = Path("/etc/docker/certs.d")
SWARM_PORT = 2377


def available() -> str | None:
    """Return why a second engine cannot run here, or None when it can."""
    if os.geteuid() != 0:
        return "needs root (dockerd, ip netns)"
    for tool in ("dockerd", "docker", "ip", "nsenter"):
        if shutil.which(tool) is None:
            return f"{tool} is not installed (scripts/services.sh docker)"
    return None


def _unmount_under(path: Path) -> None:
    """Lazily unmount whatever a dead engine left mounted below ``path`` (overlays, netns files, shm)."""
    mounts = Path("/proc/mounts").read_text().splitlines()
    points = sorted((line.split()[1] for line in mounts if line.split()[1].startswith(f"{path}/")), reverse=True)
    for point in points:
        run("umount", "-l", point, check=False)


def remove_stale() -> None:
    """Stop engines of runs whose process is gone and delete their directories."""
    for base in (EXEC, DATA):
        if not base.is_dir():
            continue
        for entry in base.iterdir():
            match = re.fullmatch(rf"{PREFIX}([0-9a-f]+)-.*", entry.name)
            if not match or _pid_alive(int(match.group(1), 16)):
                continue
            pid_file = EXEC / entry.name / "docker.pid"
            with contextlib.suppress(OSError, ValueError):
                os.kill(int(pid_file.read_text()), signal.SIGKILL)
            _unmount_under(entry)
            shutil.rmtree(entry, ignore_errors=True)


class Engine:
    """A dockerd of its own in ``namespace``; ``start()``, drive it with :meth:`docker` or :attr:`url`, ``close()``."""

    def __init__(self, namespace: str, name: str, *, address: str = "") -> None:
        self.namespace = namespace
        self.name = f"{PREFIX}{os.getpid():x}-{name}"
        self.address = address  # the namespace's own address, which a Swarm manager reaches it by
        self.data_root = DATA / self.name
        self.exec_root = EXEC / self.name
        self.socket = self.exec_root / "docker.sock"
        self.log = self.exec_root / "dockerd.log"
        self.process: subprocess.Popen[bytes] | None = None
        self.node_id = ""
        self.trusted: list[Path] = []
        self._bridge: PortBridge | None = None

    @property
    def url(self) -> str:
        """Return the engine's API address, for the Docker SDK or ``DOCKER_HOST``."""
        return f"unix://{self.socket}"

    def start(self, timeout: float = 60.0) -> Engine:
        """Start dockerd in the namespace and wait until it answers; undo everything if it does not."""
        remove_stale()
        for path in (self.data_root, self.exec_root):
            path.mkdir(parents=True, exist_ok=True)
        config = self.exec_root / "daemon.json"
        config.write_text(json.dumps({}))  # never the machine's /etc/docker/daemon.json
        command = [
            # nsenter, not `ip netns exec`: that remounts /sys, hiding the cgroup tree dockerd needs.
            "nsenter", f"--net=/run/netns/{self.namespace}", "dockerd",
            "--data-root", str(self.data_root),
            "--exec-root", str(self.exec_root),
            "--pidfile", str(self.exec_root / "docker.pid"),
            "--host", self.url,
            "--config-file", str(config),
            "--storage-driver", "overlay2",
            "--cgroup-parent", self.name,
            "--containerd-namespace", self.name,
            "--containerd-plugins-namespace", f"{self.name}-plugins",
            "--log-level", "warn",
        ]  # fmt: skip
        with self.log.open("ab") as log:
            self.process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                said = self._tail()
                self.close()
                raise RuntimeError(f"dockerd {self.name} exited: {said}")
            if self.socket.exists() and self.docker("version", check=False, timeout=10).returncode == 0:
                return self
            time.sleep(0.2)
        said = self._tail()
        self.close()
        raise RuntimeError(f"dockerd {self.name} did not answer within {timeout:.0f} s: {said}")

    def docker(self, *args: str, check: bool = True, timeout: float = 120.0) -> subprocess.CompletedProcess:
        """Run the docker CLI against this engine."""
        return run("docker", "--host", self.url, *args, check=check, timeout=timeout)

    def trust(self, registry: str, ca_pem: str) -> None:
        """Make engines on this machine verify ``registry`` (HOST:PORT) with this CA (certs.d)."""
        directory = CERTS / registry
        directory.mkdir(parents=True, exist_ok=True)
        (directory / "ca.crt").write_text(ca_pem)
        self.trusted.append(directory)

    def join_swarm(self, timeout: float = 60.0) -> str:
        """Join this machine's Swarm as a worker; return the node's id once the manager sees it ready."""
        if not self.address:
            raise ValueError("a Swarm worker needs the namespace's address (Engine(address=...))")
        token = run("docker", "swarm", "join-token", "--quiet", "worker").stdout.strip()
        # The manager advertises 127.0.0.1 (scripts/services.sh); inside the namespace that address
        # reaches the manager through a relay, so the worker finds it wherever it reconnects.
        self._bridge = PortBridge(self.namespace, SWARM_PORT)
        self.docker(
            "swarm", "join", "--token", token,
            "--advertise-addr", self.address, "--listen-addr", f"{self.address}:{SWARM_PORT}",
            f"127.0.0.1:{SWARM_PORT}",
        )  # fmt: skip
        self.node_id = self.docker("info", "--format", "{{.Swarm.NodeID}}").stdout.strip()
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            state = run("docker", "node", "inspect", self.node_id, "--format", "{{.Status.State}}", check=False)
            if state.stdout.strip() == "ready":
                return self.node_id
            time.sleep(0.5)
        raise RuntimeError(f"node {self.node_id} of {self.name} was not ready within {timeout:.0f} s")

    def close(self) -> None:
        """Leave the Swarm, stop dockerd and its containers, and delete everything it made (safe twice)."""
        if self.node_id:
            self.docker("swarm", "leave", "--force", check=False, timeout=30)
            run("docker", "node", "rm", "--force", self.node_id, check=False)
            self.node_id = ""
        if self._bridge is not None:
            self._bridge.close()
            self._bridge = None
        process, self.process = self.process, None
        if process is not None and process.poll() is None:
            os.killpg(process.pid, signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait(timeout=10)
        # Shims and containers of the engine outlive a killed dockerd: they are in its namespace.
        for pid in run("ip", "netns", "pids", self.namespace, check=False).stdout.split():
            with contextlib.suppress(ProcessLookupError, ValueError):
                os.kill(int(pid), signal.SIGKILL)
        for path in (self.exec_root, self.data_root):
            _unmount_under(path)
            shutil.rmtree(path, ignore_errors=True)
        for directory in self.trusted:
            shutil.rmtree(directory, ignore_errors=True)
        self.trusted.clear()

    def _tail(self) -> str:
        try:
            return self.log.read_text(errors="replace")[-2000:]
        except OSError:
            return "(no log)"

    def __enter__(self) -> Engine:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
