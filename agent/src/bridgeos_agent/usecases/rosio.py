"""What every use-case node shares: metrics to the Components API, loss counting, message conversions."""

from __future__ import annotations

import json
import math
import os
import queue
import sys
import threading
import time
import urllib.error
import urllib.request
from typing import Any

import numpy as np

from bridgeos_agent.usecases.motion import Pose

__all__ = [
    "XYZ_DTYPE",
    "LossCounter",
    "Metrics",
    "cloud_message",
    "cloud_xyz",
    "grid_from_message",
    "grid_message",
    "parse_points",
    "pose_of",
    "quaternion",
    "yaw_of",
]

# rospy reads each connection's messages into a buffer this large; a smaller one than a
# message makes a queue_size=1 subscriber fall behind instead of dropping stale clouds.
BIG_BUFFER = 1 << 27
# A sampled cloud's points: x y z float32, packed.
XYZ_DTYPE = np.dtype({"names": ["x", "y", "z"], "formats": ["<f4"] * 3, "offsets": [0, 4, 8], "itemsize": 12})


class Metrics:
    """Report a node's performance figures on stdout and, when set, to its Skill's Components API.

    Points are batched by a background thread and posted to ``BRIDGEOS_MANAGER_URL/metrics``
    about once a second, so a slow or absent manager never stalls the node.
    """

    def __init__(self, node: str, interval: float = 1.0, max_pending: int = 1000) -> None:
        self.node = node
        self.url = (os.environ.get("BRIDGEOS_MANAGER_URL") or "").rstrip("/") or None
        self.component = os.environ.get("BRIDGEOS_COMPONENT") or None
        self.location = os.environ.get("BRIDGEOS_LOCATION") or None
        self.interval = interval
        self.sent = 0
        self.failed = 0
        self._pending: queue.Queue[dict[str, Any]] = queue.Queue(maxsize=max_pending)
        self._stop = threading.Event()
        self._last_error = 0.0
        self._thread: threading.Thread | None = None
        if self.url:
            self._thread = threading.Thread(target=self._run, name="metrics", daemon=True)
            self._thread.start()

    def report(self, name: str, value: float, **labels: str) -> None:
        """Record one figure: printed now, posted with the next batch."""
        extra = "".join(f" {k}={v}" for k, v in labels.items())
        print(f"[{self.node}] metric {name}={value:.6g}{extra}", flush=True)
        if not self.url or not math.isfinite(value):
            return
        point: dict[str, Any] = {"name": name, "value": float(value), "ts": time.time()}
        if self.component:
            point["component"] = self.component
        tags = dict(labels)
        if self.location:
            tags.setdefault("location", self.location)
        if tags:
            point["labels"] = tags
        try:
            self._pending.put_nowait(point)
        except queue.Full:
            self.failed += 1  # the manager is unreachable for long: keep the newest, drop this one

    def close(self) -> None:
        """Post what is still pending and stop the thread."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._flush()

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self._flush()

    def _flush(self) -> None:
        batch: list[dict[str, Any]] = []
        while len(batch) < 1000:
            try:
                batch.append(self._pending.get_nowait())
            except queue.Empty:
                break
        if not batch or not self.url:
            return
        body = json.dumps({"metrics": batch}).encode()
        request = urllib.request.Request(
            f"{self.url}/metrics", data=body, method="POST", headers={"Content-Type": "application/json"}
        )
        try:
            with urllib.request.urlopen(request, timeout=5) as answer:
                answer.read()
            self.sent += len(batch)
        except (OSError, urllib.error.URLError) as exc:
            self.failed += len(batch)
            now = time.monotonic()
            if now - self._last_error > 60:
                self._last_error = now
                print(f"[{self.node}] could not post metrics to {self.url}: {exc}", file=sys.stderr, flush=True)


class LossCounter:
    """Count messages lost on a topic from gaps in their header sequence numbers."""

    def __init__(self) -> None:
        self.received = 0
        self.missing = 0
        self._last: int | None = None

    def update(self, seq: int) -> None:
        """Account for one received message."""
        self.received += 1
        if self._last is not None:
            if seq > self._last:
                self.missing += seq - self._last - 1
            # seq <= last: the publisher restarted (or moved); count from here.
        self._last = seq

    @property
    def loss_pct(self) -> float:
        """Return the percentage of messages that never arrived."""
        total = self.received + self.missing
        return 100.0 * self.missing / total if total else 0.0


def quaternion(theta: float) -> tuple[float, float, float, float]:
    """Return the (x, y, z, w) quaternion of a rotation about z."""
    return 0.0, 0.0, math.sin(theta / 2), math.cos(theta / 2)


def yaw_of(orientation: Any) -> float:
    """Return the rotation about z of a geometry_msgs/Quaternion."""
    q = orientation
    return math.atan2(2 * (q.w * q.z + q.x * q.y), 1 - 2 * (q.y * q.y + q.z * q.z))


def pose_of(message: Any) -> Pose:
    """Return the planar pose of a geometry_msgs/Pose."""
    return Pose(message.position.x, message.position.y, yaw_of(message.orientation))


def cloud_message(header: Any, points: np.ndarray, height: int = 1) -> Any:
    """Build a sensor_msgs/PointCloud2 from a structured array of float32 fields (x, y, z[, rgb])."""
    from sensor_msgs.msg import PointCloud2, PointField

    dtype = points.dtype
    if dtype.fields is None or dtype.names is None:
        raise ValueError("points must be a structured array with named float32 fields")
    fields = [
        PointField(name=name, offset=dtype.fields[name][1], datatype=PointField.FLOAT32, count=1)
        for name in dtype.names
    ]
    width = points.size // height
    return PointCloud2(
        header=header,
        height=height,
        width=width,
        fields=fields,
        is_bigendian=False,
        point_step=dtype.itemsize,
        row_step=dtype.itemsize * width,
        data=points.tobytes(),
        is_dense=False,
    )


def parse_points(message: Any) -> np.ndarray:
    """Return a PointCloud2's float32 fields as a structured array over its bytes (no copy)."""
    float32 = 7  # sensor_msgs/PointField.FLOAT32
    fields = [f for f in message.fields if f.datatype == float32 and f.count == 1]
    dtype = np.dtype(
        {
            "names": [f.name for f in fields],
            "formats": [">f4" if message.is_bigendian else "<f4"] * len(fields),
            "offsets": [f.offset for f in fields],
            "itemsize": message.point_step,
        }
    )
    count = message.width * message.height
    return np.frombuffer(message.data, dtype=dtype, count=count)


def cloud_xyz(message: Any) -> np.ndarray:
    """Return a PointCloud2's points as an (N, 3) float32 array."""
    points = parse_points(message)
    missing = {"x", "y", "z"} - set(points.dtype.names or ())
    if missing:
        raise ValueError(f"pointcloud has no {', '.join(sorted(missing))} field")
    xyz = np.empty((points.size, 3), dtype=np.float32)
    for column, name in enumerate("xyz"):
        xyz[:, column] = points[name]
    return xyz


def grid_message(header: Any, values: np.ndarray, resolution: float, origin: tuple[float, float]) -> Any:
    """Build a nav_msgs/OccupancyGrid from int8 occupancy values (row = y)."""
    from nav_msgs.msg import MapMetaData, OccupancyGrid

    info = MapMetaData(resolution=resolution, width=values.shape[1], height=values.shape[0])
    info.map_load_time = header.stamp
    info.origin.position.x, info.origin.position.y = float(origin[0]), float(origin[1])  # ROS 2 wants floats
    info.origin.orientation.w = 1.0
    return OccupancyGrid(header=header, info=info, data=values.astype(np.int8).reshape(-1).tolist())


def grid_from_message(message: Any) -> tuple[np.ndarray, float, tuple[float, float]]:
    """Return an OccupancyGrid's values (height x width int8), resolution and origin."""
    info = message.info
    values = np.asarray(message.data, dtype=np.int8).reshape(info.height, info.width)
    return values, float(info.resolution), (info.origin.position.x, info.origin.position.y)
