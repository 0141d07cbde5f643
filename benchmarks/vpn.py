"""Benchmark the robot⇄cloud VPN: tunnel setup time, added latency and throughput against the bare link.

A cloud and a robot are network namespaces joined by a veth link; the cloud runs OpenVPN with
the server config, certificates and client-config-dir entry bridgeOS renders (network.openvpn,
network.pki), the robot the client profile the cloud would serve it. In the same run it measures:

- tunnel_up_s: from starting the robot's OpenVPN to "Initialization Sequence Completed" (median);
- vpn_latency_ms / direct_latency_ms: ICMP round trip to the cloud through the tunnel / over the link (median);
- vpn_throughput_mbps (and direct_throughput_mbps): one TCP stream robot -> cloud for a few seconds.

Needs root, iproute2, openvpn and ping (scripts/services.sh vpn). Run: .venv/bin/python benchmarks/vpn.py [--quick]
"""

from __future__ import annotations

import re
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks._common import log
from benchmarks._harness import arguments, report
from network import openvpn, pki
from tests.net.netns import Network, _in_namespace, available

GOAL = {"vpn_latency_ms": 0.37, "direct_latency_ms": 0.10}  # issue 11: OpenVPN 2.6 in namespaces, measured here
SERVER_IP, CLOUD_LINK, ROBOT_LINK = "10.8.0.1", "10.255.9.1", "10.255.9.2"
LOCAL, CLOUD = "10.64.0.0/24", "10.80.0.0/24"
PORT = 5201


def write_files(directory: Path) -> Path:
    """Render the server's directory and the robot's profile as the cloud does; return the profile."""
    now = datetime.now(UTC)
    ca_key, ca = pki.make_ca("bridgeOS benchmark CA", now=now)
    server_key, server = pki.issue(ca_key, ca, openvpn.SERVER_NAME, server=True, now=now)
    client_key, client = pki.issue(ca_key, ca, "bench-robot", server=False, now=now)
    tls_crypt = pki.tls_crypt_key()
    files = {
        "server.conf": openvpn.server_config(
            device="bosnet-bsrv",
            proto="udp",
            port=1194,
            vpn_network="10.8.0.0/24",
            server_ip=SERVER_IP,
            local_pools=[LOCAL],
        ),
        "ca.crt": pki.pem(ca),
        "server.crt": pki.pem(server),
        "server.key": pki.key_pem(server_key),
        "tls-crypt.key": tls_crypt,
        "crl.pem": pki.pem(pki.make_crl(ca_key, ca, [], now=now)),
        "ccd/bench-robot": openvpn.ccd_entry(
            robot="bench-robot", tunnel="10.8.0.2/32", vpn_network="10.8.0.0/24", local=LOCAL, cloud=CLOUD
        ),
        "client.ovpn": openvpn.client_profile(
            robot="bench-robot",
            remotes=[f"{CLOUD_LINK}:1194"],
            proto="udp",
            ca_pem=pki.pem(ca),
            cert_pem=pki.pem(client),
            key_pem=pki.key_pem(client_key),
            tls_crypt=tls_crypt,
        ),
    }
    (directory / "ccd").mkdir(parents=True)
    for name, text in files.items():
        (directory / name).write_text(text)
        (directory / name).chmod(0o600)
    return directory / "client.ovpn"


def wait_for(path: Path, text: str, process: subprocess.Popen, timeout: float = 30.0) -> None:
    """Wait until a log says ``text``, polling every few milliseconds."""
    deadline = time.monotonic() + timeout
    while text not in (path.read_text(errors="replace") if path.exists() else ""):
        if process.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"{path.name}: no {text!r} (exit {process.poll()}):\n{path.read_text()[-2000:]}")
        time.sleep(0.005)


def start(net: Network, namespace: str, args: list[str], log_path: Path) -> subprocess.Popen:
    with log_path.open("wb") as out:
        return subprocess.Popen(net.command(namespace, args), stdout=out, stderr=subprocess.STDOUT)


def stop(process: subprocess.Popen) -> None:
    if process.poll() is None:
        process.terminate()
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(5)


def ping_ms(net: Network, namespace: str, target: str, count: int) -> float:
    """Return the median ICMP round trip in milliseconds."""
    out = net.exec(namespace, "ping", "-n", "-c", str(count), "-i", "0.01", target, timeout=120).stdout
    times = [float(t) for t in re.findall(r"time=([\d.]+) ms", out)]
    if len(times) < count * 0.9:
        raise RuntimeError(f"ping {target}: {len(times)} of {count} answered")
    return statistics.median(times)


def throughput_mbps(cloud: str, robot: str, target: str, seconds: float) -> float:
    """Send one TCP stream from the robot to the cloud for ``seconds``; return what arrived, in Mbit/s."""
    listener: socket.socket = _in_namespace(cloud, lambda: socket.create_server((target, PORT)))  # type: ignore[assignment]
    received = [0, 0.0, 0.0]

    def receive() -> None:
        conn, _ = listener.accept()
        with conn:
            received[1] = time.perf_counter()
            while chunk := conn.recv(1 << 20):
                received[0] += len(chunk)
            received[2] = time.perf_counter()

    reader = threading.Thread(target=receive)
    reader.start()
    sender: socket.socket = _in_namespace(robot, lambda: socket.create_connection((target, PORT), timeout=10))  # type: ignore[assignment]
    payload = b"\0" * (1 << 16)
    deadline = time.perf_counter() + seconds
    with sender:
        while time.perf_counter() < deadline:
            sender.sendall(payload)
    reader.join(60)
    listener.close()
    return received[0] * 8 / 1e6 / max(1e-6, received[2] - received[1])


def main() -> None:
    parser = arguments(__doc__, "fewer trials (under a minute)")
    args = parser.parse_args()
    why_not = available()
    if why_not:
        raise SystemExit(f"benchmarks/vpn.py: {why_not}")
    trials, pings, seconds = (3, 100, 2.0) if args.quick else (10, 500, 5.0)
    with open("/proc/loadavg") as load:
        log(f"load average before: {load.read().split()[0]} (2 cores shared)")
    net = Network()
    work = Path(tempfile.mkdtemp(prefix=f"bosnet-{net.tag}-bench-"))
    processes: list[subprocess.Popen] = []
    try:
        cloud, robot = net.host("cloud", forward=True), net.host("robot", forward=True)
        net.link(cloud, f"{CLOUD_LINK}/30", robot, f"{ROBOT_LINK}/30")
        profile = write_files(work)
        server = start(net, cloud, ["openvpn", "--cd", str(work), "--config", "server.conf"], work / "server.log")
        processes.append(server)
        wait_for(work / "server.log", "Initialization Sequence Completed", server)
        log("OpenVPN server up in the cloud namespace")

        ups = []
        client = None
        for trial in range(trials):
            client_log = work / f"client-{trial}.log"
            began = time.perf_counter()
            client = start(net, robot, ["openvpn", "--config", str(profile), "--dev", "bosnet-bcli"], client_log)
            processes.append(client)
            wait_for(client_log, "Initialization Sequence Completed", client)
            ups.append(time.perf_counter() - began)
            log(f"tunnel up in {ups[-1]:.3f} s (trial {trial + 1}/{trials})")
            if trial < trials - 1:
                stop(client)
                time.sleep(0.2)  # the server forgets the old session (explicit-exit-notify)
        direct_ms = ping_ms(net, robot, CLOUD_LINK, pings)
        vpn_ms = ping_ms(net, robot, SERVER_IP, pings)
        log(f"ping: {vpn_ms:.3f} ms through the tunnel, {direct_ms:.3f} ms on the bare link")
        direct_mbps = throughput_mbps(cloud, robot, CLOUD_LINK, seconds)
        vpn_mbps = throughput_mbps(cloud, robot, SERVER_IP, seconds)
        log(f"TCP: {vpn_mbps:.0f} Mbit/s through the tunnel, {direct_mbps:.0f} Mbit/s on the bare link")
    finally:
        for process in processes:
            stop(process)
        net.close()
    with open("/proc/loadavg") as load:
        log(f"load average after: {load.read().split()[0]}")
    result = {
        "tunnel_up_s": round(statistics.median(ups), 3),
        "vpn_latency_ms": round(vpn_ms, 3),
        "direct_latency_ms": round(direct_ms, 3),
        "vpn_throughput_mbps": round(vpn_mbps, 1),
        "direct_throughput_mbps": round(direct_mbps, 1),
    }
    print(f"tunnel setup (median of {trials}): {result['tunnel_up_s']:.3f} s   (thesis/issue: no figure)")
    print(f"latency through the VPN: {result['vpn_latency_ms']:.3f} ms   (issue: {GOAL['vpn_latency_ms']} ms)")
    print(f"latency on the bare link: {result['direct_latency_ms']:.3f} ms   (issue: {GOAL['direct_latency_ms']} ms)")
    added_goal = GOAL["vpn_latency_ms"] - GOAL["direct_latency_ms"]
    print(f"added latency: {vpn_ms - direct_ms:.3f} ms   (issue: {added_goal:.2f} ms)")
    print(
        f"throughput: {result['vpn_throughput_mbps']:.0f} Mbit/s through the VPN, "
        f"{result['direct_throughput_mbps']:.0f} Mbit/s bare ({vpn_mbps / max(direct_mbps, 1e-9):.0%}; "
        "thesis §5.2: the testbed's 220 Mbit/s LAN)"
    )
    report(result)


if __name__ == "__main__":
    main()
