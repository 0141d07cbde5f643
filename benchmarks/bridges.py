#!/usr/bin/env python3
"""Issues 19 and 32: rosbridge and Foxglove clients of a robot through the cloud, against the robot's own doors.

    .venv/bin/python benchmarks/bridges.py [--quick]

Real parts throughout: a daphne of its own (PostgreSQL, Redis), a `bridgeos-agent run` process
connected to it over a socket and serving `--rosbridge`/`--foxglove` locally too, a private
rosmaster with rospy talkers (Debian's ROS 1), and WebSocket clients speaking each protocol.

Figures: 100-byte std_msgs/String messages/s to one viewer through the cloud (rosbridge and
Foxglove) beside the same at the robot's local door; the latency the cloud adds over the local
door (stamped by the talker, paired per message); one rosbridge client's messages/s to another on
the robot's local door (the node loops them back to itself: issue 32); a 1 MB PointCloud2 at 10 Hz to 10 viewers
through the cloud's Foxglove door (p95 lag, and the robot-link bytes over the bytes delivered:
each cloud crosses the link once, as a blob, however many viewers get it); JSON vs CBOR for a 640x480 image through the
rosbridge engine (rosbridge_suite issue #367: JSON 269 ms / 11.5 MB, CBOR 1.5 ms / 0.92 MB); the
recorder's MCAP write MB/s. The last stdout line is one JSON object of them.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import struct
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _bridges_clients import (
    bridge_to_bridge,
    cloud_lags,
    count_messages,
    foxglove_subscribe,
    rosbridge_subscribe,
    stamps,
)
from _common import free_port, log, percentile
from _harness import HOST_PYTHON, arguments, cloud, report, ros_env, rosmaster, stop_process

MIB = 1024 * 1024

# A rospy talker: 100-byte strings flat out or at a rate ("seq stamp padding"), or 1 MB point clouds.
TALKER = r"""
import sys, time
import rospy
from std_msgs.msg import String
from sensor_msgs.msg import PointCloud2, PointField
kind, topic, rate = sys.argv[1], sys.argv[2], float(sys.argv[3])
rospy.init_node("bench_talker", anonymous=True, disable_signals=True)
if kind == "string":
    pub = rospy.Publisher(topic, String, queue_size=None)
else:
    pub = rospy.Publisher(topic, PointCloud2, queue_size=None)
    width = (1 << 20) // 16
    fields = [PointField(n, 4 * i, PointField.FLOAT32, 1) for i, n in enumerate(("x", "y", "z", "intensity"))]
    blob = bytes(range(256)) * ((width * 16) // 256)
print("ready", flush=True)
period = 1.0 / rate if rate > 0 else 0.0
seq = 0
next_at = time.monotonic()
while not rospy.is_shutdown():
    seq += 1
    if kind == "string":
        head = "%d %.6f " % (seq, time.time())
        pub.publish(String(data=head + "x" * (100 - len(head))))
    else:
        cloud = PointCloud2(height=1, width=width, fields=fields, is_bigendian=False, point_step=16,
                            row_step=16 * width, data=blob, is_dense=True)
        cloud.header.seq = seq
        cloud.header.stamp = rospy.Time.from_sec(time.time())
        pub.publish(cloud)
    if period:
        next_at += period
        delay = next_at - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -0.5:
            next_at = time.monotonic()
"""


# ---------------------------------------------------------------------------- ROS 1 parts


class Talkers:
    """The rospy talkers the benchmark starts and stops per phase, on a private rosmaster."""

    def __init__(self, uri: str, home: Path) -> None:
        self.uri = uri
        self.home = home

    def talker(self, kind: str, topic: str, rate: float) -> subprocess.Popen[bytes]:
        """Start a talker of 100-byte strings or 1 MB point clouds on a topic at ``rate`` Hz (0: flat out)."""
        out = (self.home / f"talker{topic.replace('/', '_')}.out").open("wb")
        process = subprocess.Popen(
            [HOST_PYTHON, "-c", TALKER, kind, topic, str(rate)],
            env=ros_env(self.uri, self.home),
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        out.close()
        return process


# ---------------------------------------------------------------------------- engine-only figures


def image_json_vs_cbor(repeats: int) -> dict[str, float]:
    """Encode a 640x480 rgb8 image as the rosbridge engine does: JSON, CBOR, CBOR-raw; ms and MB each."""
    from bridgeos_agent.bridges.graph import Sample
    from bridgeos_agent.bridges.ros1types import Ros1Types
    from bridgeos_agent.bridges.rosbridge import encode_cbor, encode_json

    types = Ros1Types()
    name = types.ensure_message("sensor_msgs/Image")
    pixels = bytes((i * 7) % 251 for i in range(640 * 480 * 3))
    raw = types.encode(
        name,
        {
            "header": {"seq": 1, "stamp": {"secs": 1, "nsecs": 2}, "frame_id": "camera"},
            "height": 480,
            "width": 640,
            "encoding": "rgb8",
            "is_bigendian": 0,
            "step": 640 * 3,
            "data": pixels,
        },
    )

    def decode(data: Any) -> dict[str, Any]:
        return types.decode(name, data)

    figures: dict[str, float] = {}
    encoders = {
        "json": lambda s: encode_json({"op": "publish", "topic": "/image", "msg": s.msg()}),
        "cbor": lambda s: encode_cbor({"op": "publish", "topic": "/image", "msg": s.msg()}),
        "cbor_raw": lambda s: encode_cbor(
            {"op": "publish", "topic": "/image", "msg": {"secs": 1, "nsecs": 2, "bytes": bytes(s.raw)}}
        ),
    }
    for label, encode in encoders.items():
        times, size = [], 0
        for _ in range(repeats):
            sample = Sample(raw, decode, (1, 2))  # a fresh message: its decoding is part of the cost
            started = time.perf_counter()
            frame = encode(sample)
            times.append((time.perf_counter() - started) * 1000)
            size = len(frame.encode() if isinstance(frame, str) else frame)
        figures[f"image_{label}_ms"] = round(sorted(times)[len(times) // 2], 2)
        figures[f"image_{label}_mb"] = round(size / 1e6, 3)
    return figures


def mcap_write(directory: Path, seconds: float) -> float:
    """Return the MB/s of message bytes the recorder turns into MCAP on disk (1 MB point clouds, zstd)."""
    from bridgeos_agent.bridges.recorder import McapRecording
    from bridgeos_agent.bridges.ros1types import Ros1Types

    types = Ros1Types()
    name = types.ensure_message("sensor_msgs/PointCloud2")
    definition = types.definition("sensor_msgs/PointCloud2")[0]
    width = MIB // 16
    # Points on a slowly varying surface: compressible as real scans are, not a repeated constant.
    points = bytearray()
    for i in range(width):
        points += struct.pack("<ffff", (i % 512) * 0.01, (i // 512) * 0.01, ((i * 2654435761) % 1000) * 1e-3, i % 97)
    fields = [{"name": n, "offset": 4 * k, "datatype": 7, "count": 1} for k, n in enumerate("xyz")]
    raw = types.encode(
        name,
        {
            "header": {"seq": 0, "stamp": {"secs": 0, "nsecs": 0}, "frame_id": "lidar"},
            "height": 1,
            "width": width,
            "fields": fields,
            "is_bigendian": False,
            "point_step": 16,
            "row_step": 16 * width,
            "data": bytes(points),
            "is_dense": True,
        },
    )
    now = time.time_ns()
    recording = McapRecording("ros1", max_bytes=1 << 40, max_duration_ns=1 << 62, started_ns=now)
    written = 0
    with (directory / "bench.mcap").open("wb") as out:
        started = time.perf_counter()
        count = 0
        while time.perf_counter() - started < seconds:
            recording.add("/points", "sensor_msgs/PointCloud2", lambda: ("ros1msg", definition), raw, now + count)
            count += 1
            for chunk in recording.take():
                written += out.write(chunk)
        for chunk in recording.finish():
            written += out.write(chunk)
        out.flush()
        os.fsync(out.fileno())
        elapsed = time.perf_counter() - started
    log(f"MCAP: {count} x {len(raw) / MIB:.2f} MiB in {elapsed:.2f} s, {written / MIB:.1f} MiB on disk")
    return count * len(raw) / 1e6 / elapsed


# ---------------------------------------------------------------------------- the cloud run


def prepare() -> tuple[str, str]:
    """Create the robot and its owner; return the robot's token and the owner's API token."""
    from django.contrib.auth import get_user_model

    from robots.models import Robot
    from robots.services import create_robot, issue_api_token

    Robot.objects.filter(id="bench-bridges").delete()
    owner, _ = get_user_model().objects.get_or_create(username="bench-bridges")
    _, token = create_robot("bench-bridges", owner)
    return token, issue_api_token(owner)[0]


def wait_connected(timeout: float = 30) -> None:
    from robots.models import Robot

    deadline = time.monotonic() + timeout
    while not Robot.objects.filter(id="bench-bridges", connected=True).exists():
        if time.monotonic() > deadline:
            raise RuntimeError("the agent did not connect to the cloud")
        time.sleep(0.2)


async def measure(args: argparse.Namespace, ros: Talkers, cloud: str, local: dict[str, str], api_token: str) -> dict:
    headers = {"Authorization": f"Token {api_token}"}
    rosbridge_cloud = f"{cloud}/ws/rosbridge/bench-bridges/"
    foxglove_cloud = f"{cloud}/ws/foxglove/bench-bridges/"
    figures: dict[str, Any] = {}
    seconds, warmup = (3.0, 1.0) if args.quick else (10.0, 2.0)

    # 1. Throughput to one viewer: the talker flat out, each door in turn.
    talker = ros.talker("string", "/flood", 0)
    try:
        doors = [
            ("rosbridge_local", "rosbridge", local["rosbridge"], None),
            ("rosbridge", "rosbridge", rosbridge_cloud, headers),
            ("foxglove_local", "foxglove", local["foxglove"], None),
            ("foxglove", "foxglove", foxglove_cloud, headers),
        ]
        for label, kind, url, hdrs in doors:
            if kind == "rosbridge":
                websocket = await rosbridge_subscribe(url, hdrs, "/flood")
            else:
                websocket = await foxglove_subscribe(url, hdrs, "/flood")
            rate = await count_messages(websocket, kind, warmup, seconds)
            await websocket.close()
            figures[f"{label}_msgs_per_s"] = round(rate)
            log(f"{label}: {rate:,.0f} msgs/s of 100-byte strings to one viewer")
            await asyncio.sleep(0.5)
    finally:
        stop_process(talker)

    # 2. Bridge to bridge: one client publishing flat out, another subscribed, on the robot's local door.
    rate, delivered = await bridge_to_bridge(local["rosbridge"], warmup, seconds)
    figures["bridge_to_bridge_msgs_per_s"] = round(rate)
    figures["bridge_to_bridge_delivered_ratio"] = round(delivered, 3)
    log(
        f"bridge to bridge: {rate:,.0f} msgs/s of 100-byte strings from one rosbridge client to another, "
        f"{delivered:.1%} of those sent delivered"
    )

    # 3. Added latency at a moderate rate: the local door and the cloud's, the same messages at once.
    talker = ros.talker("string", "/paced", args.latency_rate)
    try:
        local_ws = await rosbridge_subscribe(local["rosbridge"], None, "/paced")
        cloud_ws = await rosbridge_subscribe(rosbridge_cloud, headers, "/paced")
        await asyncio.sleep(warmup)
        at_local: dict[int, float] = {}
        at_cloud: dict[int, float] = {}
        await asyncio.gather(
            stamps(local_ws, "rosbridge", seconds, at_local), stamps(cloud_ws, "rosbridge", seconds, at_cloud)
        )
        await local_ws.close()
        await cloud_ws.close()
    finally:
        stop_process(talker)
    both = sorted(set(at_local) & set(at_cloud))
    added = [at_cloud[seq] - at_local[seq] for seq in both]
    figures["latency_messages"] = len(both)
    figures["local_latency_p50_ms"] = round(percentile(list(at_local.values()), 50) or 0, 2)
    figures["cloud_latency_p50_ms"] = round(percentile(list(at_cloud.values()), 50) or 0, 2)
    figures["cloud_added_latency_p50_ms"] = round(percentile(added, 50) or 0, 2)
    figures["cloud_added_latency_p95_ms"] = round(percentile(added, 95) or 0, 2)
    log(
        f"latency at {args.latency_rate:g} Hz over {len(both)} messages: "
        f"local p50 {figures['local_latency_p50_ms']} ms, "
        f"cloud p50 {figures['cloud_latency_p50_ms']} ms; added p50 {figures['cloud_added_latency_p50_ms']} ms, "
        f"p95 {figures['cloud_added_latency_p95_ms']} ms"
    )

    # 4. A 1 MB point cloud at 10 Hz to 10 viewers of the cloud's Foxglove door.
    talker = ros.talker("cloud", "/points", 10)
    try:
        viewers = [await foxglove_subscribe(foxglove_cloud, headers, "/points") for _ in range(args.viewers)]
        before = bridge_counters(cloud)
        lags: list[float] = []
        received = await asyncio.gather(*(cloud_lags(v, seconds, warmup, lags) for v in viewers))
        after = bridge_counters(cloud)
        for viewer in viewers:
            await viewer.close()
    finally:
        stop_process(talker)
    # What crossed the robot's link for the viewers (each cloud once, as a blob) over what they got.
    delivered = after["bridgeos_bridge_bytes_total"] - before["bridgeos_bridge_bytes_total"]
    shared = after["bridgeos_bridge_blob_bytes_total"] - before["bridgeos_bridge_blob_bytes_total"]
    figures["pointcloud_link_over_delivered"] = round(shared / delivered, 3) if delivered else None
    expected = 10 * seconds * args.viewers
    figures["pointcloud_10_viewers_p50_ms"] = round(percentile(lags, 50) or 0, 1)
    figures["pointcloud_10_viewers_p95_ms"] = round(percentile(lags, 95) or 0, 1)
    figures["pointcloud_delivered_ratio"] = round(sum(received) / expected, 3)
    log(
        f"1 MB PointCloud2 at 10 Hz to {args.viewers} viewers: lag p50 {figures['pointcloud_10_viewers_p50_ms']} ms, "
        f"p95 {figures['pointcloud_10_viewers_p95_ms']} ms; {sum(received)} of ~{expected:.0f} delivered"
    )
    return figures


def bridge_counters(cloud: str) -> dict[str, float]:
    """Return the cloud's bridge byte counters from its /metrics."""
    text = urllib.request.urlopen(cloud.replace("ws://", "http://") + "/metrics", timeout=10).read().decode()
    found = {"bridgeos_bridge_bytes_total": 0.0, "bridgeos_bridge_blob_bytes_total": 0.0}
    for line in text.splitlines():
        name = line.split("{", 1)[0].split(" ", 1)[0]
        if name in found:
            found[name] += float(line.rsplit(" ", 1)[1])
    return found


def table(figures: dict[str, Any]) -> None:
    rows = [
        ("rosbridge msgs/s to one viewer, cloud", "rosbridge_msgs_per_s", ">= 10,000 (issue 19)"),
        ("rosbridge msgs/s to one viewer, local door", "rosbridge_local_msgs_per_s", ""),
        ("rosbridge client to client msgs/s, local door", "bridge_to_bridge_msgs_per_s", ">= 10,000 (issue 32)"),
        ("  delivered share", "bridge_to_bridge_delivered_ratio", ""),
        ("Foxglove msgs/s to one viewer, cloud", "foxglove_msgs_per_s", ">= 10,000 (issue 19)"),
        ("Foxglove msgs/s to one viewer, local door", "foxglove_local_msgs_per_s", ""),
        ("latency added by the cloud p50 (ms)", "cloud_added_latency_p50_ms", ""),
        ("latency added by the cloud p95 (ms)", "cloud_added_latency_p95_ms", ""),
        ("1 MB PointCloud2 10 Hz, 10 viewers, lag p95 (ms)", "pointcloud_10_viewers_p95_ms", "<= 200 (issue 19)"),
        ("  delivered share", "pointcloud_delivered_ratio", ""),
        ("  robot-link bytes over bytes delivered", "pointcloud_link_over_delivered", "0.1 = one copy for 10"),
        ("640x480 image JSON (ms)", "image_json_ms", "269 (rosbridge_suite #367)"),
        ("640x480 image JSON (MB)", "image_json_mb", "11.5 (rosbridge_suite #367)"),
        ("640x480 image CBOR (ms)", "image_cbor_ms", "1.5 (rosbridge_suite #367)"),
        ("640x480 image CBOR (MB)", "image_cbor_mb", "0.92 (rosbridge_suite #367)"),
        ("640x480 image CBOR-raw (ms)", "image_cbor_raw_ms", ""),
        ("MCAP write (MB/s of messages)", "mcap_write_mb_per_s", ""),
    ]
    print(f"{'figure':<52} {'ours':>10}   reference", file=sys.stderr)
    for label, key, reference in rows:
        value = figures.get(key)
        text = "-" if value is None else f"{value:,}" if isinstance(value, int) else f"{value:g}"
        print(f"{label:<52} {text:>10}   {reference}", file=sys.stderr)


def main() -> None:
    parser = arguments(__doc__, "shorter windows (under a minute)", database="bridgeos_bench", redis=12)
    parser.add_argument("--viewers", type=int, default=10)
    parser.add_argument("--latency-rate", type=float, default=200.0, help="Hz of the latency talker")
    args = parser.parse_args()
    if not (Path(HOST_PYTHON).exists() and Path("/usr/bin/rosmaster").exists()):
        raise SystemExit("Debian's ROS 1 (rospy, rosmaster) is not installed")

    figures: dict[str, Any] = {"quick": args.quick}
    figures.update(image_json_vs_cbor(3 if args.quick else 10))
    log(
        f"640x480 image: JSON {figures['image_json_ms']} ms / {figures['image_json_mb']} MB, "
        f"CBOR {figures['image_cbor_ms']} ms / {figures['image_cbor_mb']} MB"
    )
    # Room for 10 MB/s of point clouds per viewer: the default cap (8 MiB/s) is below the case.
    env = {"BRIDGEOS_BRIDGE_CLIENT_BYTES_PER_S": str(64 * MIB)}
    with cloud(args, "bridgeos-bench-bridges-", env=env, flush_redis=False, remove_data=True) as bench:
        data = bench.data_dir
        figures["mcap_write_mb_per_s"] = round(mcap_write(data, 1.5 if args.quick else 5.0), 1)
        token, api_token = prepare()
        with rosmaster(data) as master:
            try:
                daphne = bench.start_daphne()
                ports = {"rosbridge": free_port(), "foxglove": free_port()}
                doors = [
                    "--rosbridge",
                    f"127.0.0.1:{ports['rosbridge']}",
                    "--foxglove",
                    f"127.0.0.1:{ports['foxglove']}",
                ]
                ros = {"ROS_MASTER_URI": master, "ROS_IP": "127.0.0.1"}
                bench.start_agent(daphne, "bench-bridges", token, "--simulate", *doors, env=ros)
                wait_connected()
                local = {kind: f"ws://127.0.0.1:{port}" for kind, port in ports.items()}
                figures.update(asyncio.run(measure(args, Talkers(master, data), daphne.ws_url, local, api_token)))
            finally:
                bench.stop()  # the agent and daphne before their rosmaster
    table(figures)
    report(figures)


if __name__ == "__main__":
    main()
