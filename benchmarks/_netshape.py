"""Shaped robot-cloud network: a "cloud" network namespace reachable only through a slow link.

    host (the robot)  tun bosuc-ID-r ──► relay ──► tun bosuc-ID-c  netns bosuc-ID (the cloud)
     HOST_IP            tc tbf: uplink    delay, jitter,   tc tbf: downlink   CLOUD_IP
                                          loss (user space)

Bandwidth is shaped by the kernel with ``tc`` (a token bucket on each tun's egress). Delay,
jitter and loss come from a small asyncio relay that reads every IP packet from one tun and
writes it into the other: netem does not work on this machine, and a relay at the packet
level keeps TCP honest (a lost packet is retransmitted by the real stack, not hidden) and
works for every port, so ROS's TCPROS connections and XML-RPC go through it unchanged.

Needs root, ``ip`` and ``tc`` (iproute2) and ``/dev/net/tun``. Every namespace and device is
named ``bosuc-...``; :meth:`Link.down` (also on ``with`` exit) removes them, and
:func:`clean` removes any a killed process left behind. Pure standard library, so any
python3 runs it.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import dataclasses
import fcntl
import ipaddress
import json
import os
import random
import secrets
import signal
import struct
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

__all__ = ["PREFIX", "PRESETS", "Conditions", "Link", "clean", "conditions_for", "list_links"]

PREFIX = "bosuc-"
STATE_DIR = Path(os.environ.get("BRIDGEOS_NETSHAPE_STATE", "/run/bridgeos-netshape"))
SUBNET = ipaddress.ip_network("10.213.0.0/16")  # a /30 of it per link
TUNSETIFF = 0x400454CA
IFF_TUN = 0x0001
IFF_NO_PI = 0x1000
MAX_QUEUE = 20_000  # packets held by the relay per direction before it drops


@dataclass(frozen=True)
class Conditions:
    """What the robot-cloud link is like: rates per direction, one-way delay, jitter, loss."""

    up_mbit: float  # robot -> cloud
    down_mbit: float  # cloud -> robot
    delay_ms: float = 0.0  # one way, each direction
    jitter_ms: float = 0.0  # standard deviation around the delay
    loss_pct: float = 0.0  # packets dropped, each direction

    def __post_init__(self) -> None:
        for name in ("up_mbit", "down_mbit"):
            value = getattr(self, name)
            if not 0.01 <= value <= 10_000:
                raise ValueError(f"{name} must be between 0.01 and 10000 Mbit/s, not {value}")
        if not 0 <= self.delay_ms <= 10_000 or not 0 <= self.jitter_ms <= 10_000:
            raise ValueError("delay_ms and jitter_ms must be between 0 and 10000")
        if not 0 <= self.loss_pct <= 100:
            raise ValueError(f"loss_pct must be between 0 and 100, not {self.loss_pct}")

    def as_dict(self) -> dict[str, float]:
        """Return the conditions as plain data."""
        return dataclasses.asdict(self)


# Typical figures: a LAN like the thesis's testbed, good Wi-Fi, a fair 4G cell, a poor 3G one.
PRESETS = {
    "lan": Conditions(up_mbit=1000, down_mbit=1000, delay_ms=0.1, jitter_ms=0.0, loss_pct=0.0),
    "wifi": Conditions(up_mbit=40, down_mbit=40, delay_ms=3, jitter_ms=1, loss_pct=0.1),
    "4g": Conditions(up_mbit=10, down_mbit=30, delay_ms=25, jitter_ms=5, loss_pct=0.5),
    "3g": Conditions(up_mbit=1, down_mbit=3, delay_ms=75, jitter_ms=15, loss_pct=1.0),
}


def conditions_for(preset: str | None = None, **overrides: float | None) -> Conditions:
    """Return a preset's conditions (default wifi) with any given field overridden."""
    name = preset or "wifi"
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r} (known: {', '.join(PRESETS)})")
    changes = {k: float(v) for k, v in overrides.items() if v is not None}
    return dataclasses.replace(PRESETS[name], **changes)


def _run(*command: str, check: bool = True) -> subprocess.CompletedProcess[str]:
    done = subprocess.run(command, capture_output=True, text=True, timeout=30)
    if check and done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed: {done.stderr.strip() or done.stdout.strip()}")
    return done


def _require_tools() -> None:
    problems = []
    if os.geteuid() != 0:
        problems.append("run as root (network namespaces and tc need it)")
    if not os.path.exists("/dev/net/tun"):
        problems.append("/dev/net/tun is missing (modprobe tun)")
    for tool in ("ip", "tc"):
        if _run("sh", "-c", f"command -v {tool}", check=False).returncode != 0:
            problems.append(f"{tool} is not installed (apt-get install iproute2)")
    if problems:
        raise RuntimeError("netshape cannot run: " + "; ".join(problems))


def _tbf(device: str, mbit: float, mtu: int, netns: str | None = None) -> None:
    """Shape a device's egress with a token bucket: the rate, a burst of a few ms, 400 ms of queue."""
    burst = max(2 * (mtu + 64), int(mbit * 1e6 / 8 * 0.004))
    prefix = ("ip", "netns", "exec", netns) if netns else ()
    tbf = ("tbf", "rate", f"{mbit}mbit", "burst", str(burst), "latency", "400ms")
    _run(*prefix, "tc", "qdisc", "replace", "dev", device, "root", *tbf)


def _taken_addresses() -> set[str]:
    out = _run("ip", "-4", "-o", "addr", "show", check=False).stdout
    return {part.split("/")[0] for line in out.splitlines() for part in line.split()[3:4]}


def _pick_subnet() -> tuple[str, str]:
    taken = _taken_addresses() | {str(s.get("host_ip")) for s in _states()}
    blocks = list(SUBNET.subnets(new_prefix=30))
    for _ in range(200):
        block = random.choice(blocks)
        host, cloud = (str(a) for a in list(block.hosts())[:2])
        if host not in taken and cloud not in taken:
            return host, cloud
    raise RuntimeError(f"no free /30 left in {SUBNET}")


def _states() -> list[dict[str, Any]]:
    if not STATE_DIR.is_dir():
        return []
    found = []
    for path in STATE_DIR.glob(f"{PREFIX}*.json"):
        with contextlib.suppress(OSError, ValueError):
            found.append(json.loads(path.read_text()))
    return found


def _alive(pid: int | None) -> bool:
    if not pid:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def list_links() -> list[dict[str, Any]]:
    """Describe every bosuc- namespace: its state (if known) and whether its owner still runs."""
    names = [line.split()[0] for line in _run("ip", "netns", "list", check=False).stdout.splitlines() if line.strip()]
    states = {s["name"]: s for s in _states()}
    return [
        {**states.get(name, {"name": name}), "owner_alive": _alive(states.get(name, {}).get("owner_pid"))}
        for name in names
        if name.startswith(PREFIX)
    ]


def clean(everything: bool = False) -> list[str]:
    """Remove bosuc- namespaces whose owner is gone (or all with everything=True); return their names."""
    removed = []
    links = list_links()
    for link in links:
        if everything or not link["owner_alive"]:
            _teardown(link["name"], link.get("relay_pid"))
            removed.append(link["name"])
    present = {link["name"] for link in links}
    for state in _states():
        if state.get("name") not in present:
            (STATE_DIR / f"{state.get('name')}.json").unlink(missing_ok=True)  # its namespace is gone already
    return removed


def _teardown(name: str, relay_pid: int | None) -> None:
    if relay_pid and _alive(relay_pid):
        with contextlib.suppress(ProcessLookupError):
            os.kill(relay_pid, signal.SIGTERM)
    _run("ip", "netns", "del", name, check=False)
    _run("ip", "link", "del", f"{name}r", check=False)  # only if the relay left it behind
    (STATE_DIR / f"{name}.json").unlink(missing_ok=True)


class Link:
    """One shaped robot-cloud link: ``up()``, run things in :attr:`exec_prefix`, ``set()``, ``down()``."""

    def __init__(
        self, conditions: Conditions | None = None, *, name: str | None = None, mtu: int | None = None
    ) -> None:
        self.conditions = conditions or PRESETS["wifi"]
        self.name = name or f"{PREFIX}{secrets.token_hex(3)}"
        if not self.name.startswith(PREFIX) or len(self.name) > 14 or not self.name.replace("-", "").isalnum():
            raise ValueError(f"a link name is {PREFIX} and up to 8 letters or digits, not {self.name!r}")
        fast = max(self.conditions.up_mbit, self.conditions.down_mbit) > 100
        # Big packets where the link is fast (fewer for the relay to move), Ethernet's where it is slow.
        self.mtu = mtu or (9000 if fast else 1500)
        self.host_ip = ""
        self.cloud_ip = ""
        self.relay: subprocess.Popen[str] | None = None

    @property
    def robot_device(self) -> str:
        return f"{self.name}r"

    @property
    def cloud_device(self) -> str:
        return f"{self.name}c"

    @property
    def exec_prefix(self) -> list[str]:
        """Return the command prefix that runs a program on the cloud side."""
        return ["ip", "netns", "exec", self.name]

    def up(self) -> Link:
        """Create the namespace, the tuns, the relay and the shaping; undo everything if a step fails."""
        _require_tools()
        self.host_ip, self.cloud_ip = _pick_subnet()
        STATE_DIR.mkdir(parents=True, exist_ok=True)
        try:
            _run("ip", "netns", "add", self.name)
            self.relay = subprocess.Popen(
                [sys.executable, str(Path(__file__).resolve()), self.robot_device, self.cloud_device],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                text=True,
                start_new_session=True,
            )
            ready = self.relay.stdout.readline().strip() if self.relay.stdout else ""
            if ready != "ready":
                raise RuntimeError(f"the relay did not start (said {ready!r})")
            self._save_state()
            _run("ip", "link", "set", self.cloud_device, "netns", self.name)
            for device, netns, mine, peer in (
                (self.robot_device, None, self.host_ip, self.cloud_ip),
                (self.cloud_device, self.name, self.cloud_ip, self.host_ip),
            ):
                ns = ("-n", netns) if netns else ()
                # No IPv6 on the link: its router solicitations would only be noise for the relay.
                prefix = ("ip", "netns", "exec", netns) if netns else ()
                _run(*prefix, "sysctl", "-qw", f"net.ipv6.conf.{device}.disable_ipv6=1", check=False)
                _run("ip", *ns, "addr", "add", mine, "peer", peer, "dev", device)
                _run("ip", *ns, "link", "set", device, "mtu", str(self.mtu), "up")
            _run("ip", "-n", self.name, "link", "set", "lo", "up")
            self.set(self.conditions)
        except BaseException:
            self.down()
            raise
        return self

    def set(self, conditions: Conditions) -> None:
        """Change the link's conditions now: tc for the rates, the relay for delay, jitter, loss."""
        if self.relay is None or self.relay.poll() is not None or self.relay.stdin is None:
            raise RuntimeError(f"link {self.name} is not up")
        _tbf(self.robot_device, conditions.up_mbit, self.mtu)
        _tbf(self.cloud_device, conditions.down_mbit, self.mtu, netns=self.name)
        self.relay.stdin.write(json.dumps({"set": conditions.as_dict()}) + "\n")
        self.relay.stdin.flush()
        self.conditions = conditions
        self._save_state()

    def stats(self) -> dict[str, Any]:
        """Return the relay's packet counts per direction (forwarded, dropped by loss, overflowed)."""
        if self.relay is None or self.relay.stdin is None or self.relay.stdout is None:
            raise RuntimeError(f"link {self.name} is not up")
        self.relay.stdin.write('{"stats": true}\n')
        self.relay.stdin.flush()
        return json.loads(self.relay.stdout.readline())

    def down(self) -> None:
        """Stop the relay and remove the namespace and devices (safe to call twice)."""
        relay, self.relay = self.relay, None
        if relay is not None:
            if relay.poll() is None:
                relay.terminate()
                try:
                    relay.wait(timeout=10)
                except subprocess.TimeoutExpired:
                    relay.kill()
                    relay.wait(timeout=10)
            for stream in (relay.stdin, relay.stdout):
                if stream is not None:
                    with contextlib.suppress(OSError):
                        stream.close()
        _teardown(self.name, None)

    def _save_state(self) -> None:
        state = {
            "name": self.name,
            "host_ip": self.host_ip,
            "cloud_ip": self.cloud_ip,
            "mtu": self.mtu,
            "owner_pid": os.getpid(),
            "relay_pid": self.relay.pid if self.relay else None,
            "conditions": self.conditions.as_dict(),
            "since": time.time(),
        }
        (STATE_DIR / f"{self.name}.json").write_text(json.dumps(state))

    def __enter__(self) -> Link:
        return self.up()

    def __exit__(self, *exc: object) -> None:
        self.down()


# --------------------------------------------------------------------------- the relay process


def _open_tun(name: str) -> int:
    fd = os.open("/dev/net/tun", os.O_RDWR | os.O_CLOEXEC)
    fcntl.ioctl(fd, TUNSETIFF, struct.pack("16sH", name.encode(), IFF_TUN | IFF_NO_PI))
    os.set_blocking(fd, False)
    return fd


class _Direction:
    """Carry packets one way: drop some, hold each for delay + jitter, never reorder."""

    def __init__(self, loop: asyncio.AbstractEventLoop, source: int, sink: int, rng: random.Random) -> None:
        self.loop, self.source, self.sink, self.rng = loop, source, sink, rng
        self.delay = self.jitter = self.loss = 0.0
        self.queue: collections.deque[tuple[float, bytes]] = collections.deque()
        self.last_due = 0.0
        self.timer: asyncio.TimerHandle | None = None
        self.counts = {"forwarded": 0, "lost": 0, "overflow": 0}

    def readable(self) -> None:
        for _ in range(256):  # a burst per wake-up, then let the other direction run
            try:
                packet = os.read(self.source, 65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                self.loop.stop()
                return
            if self.loss and self.rng.random() < self.loss:
                self.counts["lost"] += 1
                continue
            if not self.delay and not self.jitter and not self.queue:
                self._write(packet)
                continue
            if len(self.queue) >= MAX_QUEUE:
                self.counts["overflow"] += 1
                continue
            now = self.loop.time()
            wait = max(0.0, self.delay + (self.rng.gauss(0.0, self.jitter) if self.jitter else 0.0))
            due = max(now + wait, self.last_due)  # jitter stretches gaps but keeps the order
            self.last_due = due
            self.queue.append((due, packet))
            if self.timer is None:
                self.timer = self.loop.call_at(due, self.flush)

    def flush(self) -> None:
        self.timer = None
        now = self.loop.time()
        while self.queue and self.queue[0][0] <= now + 0.0002:
            self._write(self.queue.popleft()[1])
        if self.queue:
            self.timer = self.loop.call_at(self.queue[0][0], self.flush)

    def _write(self, packet: bytes) -> None:
        try:
            os.write(self.sink, packet)
            self.counts["forwarded"] += 1
        except (BlockingIOError, InterruptedError):
            self.counts["overflow"] += 1
        except OSError:
            self.loop.stop()


def relay_main(robot_device: str, cloud_device: str) -> int:
    """Run the relay between two tuns, taking commands as JSON lines on stdin."""
    robot = _open_tun(robot_device)
    cloud = _open_tun(cloud_device)
    loop = asyncio.new_event_loop()
    rng = random.Random()
    up = _Direction(loop, robot, cloud, rng)  # robot -> cloud
    down = _Direction(loop, cloud, robot, rng)
    loop.add_reader(robot, up.readable)
    loop.add_reader(cloud, down.readable)
    stdin = sys.stdin.fileno()
    os.set_blocking(stdin, False)
    pending = b""

    def command() -> None:
        nonlocal pending
        try:
            chunk = os.read(stdin, 65536)
        except BlockingIOError:
            return
        if not chunk:
            loop.stop()  # the owner is gone
            return
        pending += chunk
        while b"\n" in pending:
            line, pending = pending.split(b"\n", 1)
            message = json.loads(line)
            if "set" in message:
                c = Conditions(**message["set"])
                for direction in (up, down):
                    direction.delay, direction.jitter = c.delay_ms / 1000, c.jitter_ms / 1000
                    direction.loss = c.loss_pct / 100
            if message.get("stats"):
                print(json.dumps({"up": up.counts, "down": down.counts}), flush=True)

    loop.add_reader(stdin, command)
    for sig in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(sig, loop.stop)
    print("ready", flush=True)
    try:
        loop.run_forever()
    finally:
        loop.close()
        os.close(robot)
        os.close(cloud)
    return 0


if __name__ == "__main__":
    sys.exit(relay_main(sys.argv[1], sys.argv[2]))
