"""The shaped robot-cloud link: real namespaces, tc token buckets and the user-space relay.

Traffic is real TCP and UDP between this process (the robot side) and a server started in
the cloud namespace; only the link's conditions are made up. Every link is removed when its
test ends, also when it fails.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import statistics
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from benchmarks import _netshape as netshape

ROOT = Path(__file__).resolve().parent.parent.parent

SINK = """
import json, socket, sys, time
server = socket.socket()
server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
server.bind(("0.0.0.0", int(sys.argv[1])))
server.listen(1)
print("listening", flush=True)
conn, _ = server.accept()
marks = []
total = 0
while True:
    chunk = conn.recv(1 << 16)
    if not chunk:
        break
    total += len(chunk)
    marks.append((time.monotonic(), total))
print(json.dumps(marks[:: max(1, len(marks) // 2000)] + marks[-1:]), flush=True)
"""

SOURCE = """
import socket, sys, time
server = socket.socket()
server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
server.bind(("0.0.0.0", int(sys.argv[1])))
server.listen(1)
print("listening", flush=True)
conn, _ = server.accept()
end = time.monotonic() + float(sys.argv[2])
block = b"x" * 65536
while time.monotonic() < end:
    conn.sendall(block)
conn.close()
"""

ECHO = """
import socket, sys
sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
sock.bind(("0.0.0.0", int(sys.argv[1])))
print("listening", flush=True)
while True:
    data, peer = sock.recvfrom(2048)
    sock.sendto(data, peer)
"""


@pytest.fixture
def links() -> Iterator[list[netshape.Link]]:
    """Collect the links a test brings up and remove them all at its end."""
    made: list[netshape.Link] = []
    try:
        yield made
    finally:
        for link in made:
            link.down()


def up(links: list[netshape.Link], conditions: netshape.Conditions) -> netshape.Link:
    link = netshape.Link(conditions)
    links.append(link)
    return link.up()


def cloud_process(link: netshape.Link, code: str, *args: str) -> subprocess.Popen[str]:
    """Start a python snippet on the cloud side and wait until it says it listens."""
    process = subprocess.Popen(
        [*link.exec_prefix, sys.executable, "-c", code, *args],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    assert process.stdout is not None and process.stdout.readline().strip() == "listening"
    return process


def stop(process: subprocess.Popen[str]) -> None:
    if process.poll() is None:
        os.killpg(process.pid, signal.SIGKILL)
    process.wait(timeout=30)


def steady_rate_mbit(marks: list[list[float]]) -> float:
    """Return the receive rate after the first half second (TCP's slow start left out)."""
    start_t = marks[0][0] + 0.5
    begin = next(m for m in marks if m[0] >= start_t)
    end = marks[-1]
    return (end[1] - begin[1]) * 8 / 1e6 / (end[0] - begin[0])


def uplink_mbit(link: netshape.Link) -> float:
    """Send for 3.5 s to a sink on the cloud side and return its steady receive rate."""
    sink = cloud_process(link, SINK, "5001")
    try:
        with socket.create_connection((link.cloud_ip, 5001), timeout=30) as conn:
            end = time.monotonic() + 3.5
            block = b"x" * 65536
            while time.monotonic() < end:
                conn.sendall(block)
        return steady_rate_mbit(json.loads(sink.communicate(timeout=60)[0].strip().splitlines()[-1]))
    finally:
        stop(sink)


def downlink_mbit(link: netshape.Link) -> float:
    """Receive for 3.5 s from a source on the cloud side and return the steady rate."""
    source = cloud_process(link, SOURCE, "5002", "3.5")
    try:
        marks, total = [], 0
        with socket.create_connection((link.cloud_ip, 5002), timeout=30) as conn:
            conn.settimeout(30)
            while chunk := conn.recv(1 << 16):
                total += len(chunk)
                marks.append([time.monotonic(), total])
        return steady_rate_mbit(marks)
    finally:
        stop(source)


def shaped_rate(measure, link: netshape.Link, goal: float) -> float:
    """Return the best of up to three runs: the shaper is a ceiling, and a busy CI machine only ever
    measures below it (the relay is user space), so one slow run says nothing about the shaper."""
    best = 0.0
    for _ in range(3):
        best = max(best, measure(link))
        if best == pytest.approx(goal, rel=0.15):
            break
    return best


def test_the_4g_preset_shapes_both_directions_within_15_percent(links) -> None:
    preset = netshape.PRESETS["4g"]
    # Rates only: TCP under the preset's loss and delay would measure TCP, not the shaper.
    link = up(links, netshape.conditions_for("4g", delay_ms=0, jitter_ms=0, loss_pct=0))

    uplink = shaped_rate(uplink_mbit, link, preset.up_mbit)
    downlink = shaped_rate(downlink_mbit, link, preset.down_mbit)

    assert uplink == pytest.approx(preset.up_mbit, rel=0.15), f"uplink {uplink:.2f} Mbit/s"
    assert downlink == pytest.approx(preset.down_mbit, rel=0.15), f"downlink {downlink:.2f} Mbit/s"


def round_trips(link: netshape.Link, count: int, gap: float) -> tuple[list[float], int]:
    """Send numbered UDP probes to the cloud's echo server; return round trips (ms) and how many came back."""
    echo = cloud_process(link, ECHO, "5003")
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.settimeout(0.005)
            sent_at: dict[int, float] = {}
            rtts: list[float] = []
            for n in range(count):
                sent_at[n] = time.monotonic()
                sock.sendto(n.to_bytes(4, "big"), (link.cloud_ip, 5003))
                deadline = time.monotonic() + gap
                while time.monotonic() < deadline:
                    try:
                        data = sock.recv(64)
                    except TimeoutError:
                        continue
                    rtts.append((time.monotonic() - sent_at[int.from_bytes(data, "big")]) * 1000)
            sock.settimeout(1.0)
            with_deadline = time.monotonic() + 2.0
            while time.monotonic() < with_deadline:  # the last probes' answers
                try:
                    data = sock.recv(64)
                except TimeoutError:
                    break
                rtts.append((time.monotonic() - sent_at[int.from_bytes(data, "big")]) * 1000)
        return rtts, len(rtts)
    finally:
        stop(echo)


def test_delay_and_jitter_are_added_each_way(links) -> None:
    link = up(links, netshape.Conditions(up_mbit=50, down_mbit=50, delay_ms=30))
    rtts, _ = round_trips(link, 60, 0.02)
    median = statistics.median(rtts)
    assert 60 <= median <= 60 + 20, f"median round trip {median:.1f} ms for 2 x 30 ms"

    link.set(netshape.Conditions(up_mbit=50, down_mbit=50, delay_ms=30, jitter_ms=10))
    rtts, _ = round_trips(link, 150, 0.02)
    spread = statistics.stdev(rtts)
    # Two independent 10 ms jitters make ~14 ms; a loaded machine only adds to it.
    assert 7 <= spread <= 40, f"round-trip standard deviation {spread:.1f} ms"
    assert 40 <= statistics.median(rtts) <= 100


def test_loss_drops_the_configured_share_of_packets(links) -> None:
    link = up(links, netshape.Conditions(up_mbit=50, down_mbit=50, loss_pct=20))
    count = 600
    _, answered = round_trips(link, count, 0.003)
    stats = link.stats()

    # Each probe crosses the link twice: 0.8 * 0.8 come back (4 standard deviations of slack).
    assert 0.64 - 0.08 <= answered / count <= 0.64 + 0.08, f"{answered} of {count} answered"
    up_seen = stats["up"]["lost"] + stats["up"]["forwarded"]
    assert stats["up"]["lost"] / up_seen == pytest.approx(0.20, abs=0.06), stats


def test_links_are_removed_on_exit_and_orphans_by_clean() -> None:
    with netshape.Link(netshape.PRESETS["3g"]) as link:
        name = link.name
        assert name in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert name not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    assert subprocess.run(["ip", "link", "show", f"{name}r"], capture_output=True).returncode != 0

    # An owner killed outright leaves its namespace behind; clean() removes it.
    owner = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys, time; sys.path.insert(0, sys.argv[1]); import _netshape as n; "
            "link = n.Link().up(); print(link.name, flush=True); time.sleep(600)",
            str(ROOT / "benchmarks"),
        ],
        stdout=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        orphan = owner.stdout.readline().strip() if owner.stdout else ""
        assert orphan.startswith(netshape.PREFIX)
    finally:
        os.killpg(owner.pid, signal.SIGKILL)
        owner.wait(timeout=30)
    try:
        assert any(link["name"] == orphan and not link["owner_alive"] for link in netshape.list_links())
        assert orphan in netshape.clean()
        assert orphan not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    finally:
        subprocess.run(["ip", "netns", "del", orphan], capture_output=True)


def test_the_cli_runs_a_command_on_the_cloud_side_and_removes_the_link() -> None:
    done = subprocess.run(
        [
            sys.executable,
            str(ROOT / "scripts" / "netshape.py"),
            "run",
            "--preset",
            "wifi",
            "--delay-ms",
            "5",
            "--",
            "sh",
            "-c",
            "ip -4 -o addr show; echo host=$NETSHAPE_HOST_IP",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    name = done.stdout.split()[1].rstrip(":")
    assert name.startswith(netshape.PREFIX)
    assert "delay 5 ms" in done.stdout and f"{name}c" in done.stdout and "host=10.213." in done.stdout
    assert f"link {name} removed" in done.stdout
    assert name not in subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout

    bad = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "netshape.py"), "run", "--loss-pct", "120", "--", "true"],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode != 0 and "loss_pct must be between 0 and 100" in bad.stderr + bad.stdout
