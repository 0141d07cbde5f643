"""People Detection's People Detector on ROS 2: find people in ``pointcloud_sampled``, publish ``people``.

The same detection as the ROS 1 node (geometry_msgs/PoseArray out, ``pointcloud_processing_ms``
from the camera's stamp, ``GET /detections`` with ``--http-port``).
"""

from __future__ import annotations

import time
from typing import Any

from bridgeos_agent.usecases import detector
from bridgeos_agent.usecases.detection import DetectorSettings, detect_people
from bridgeos_agent.usecases.ros2.node import node_args, reliable, seq, spin, stamp_ns, start, subscribe_counted
from bridgeos_agent.usecases.rosio import LossCounter, Metrics, cloud_xyz


def main(argv: list[str]) -> int:
    args = detector.parse_args(node_args(argv))
    from geometry_msgs.msg import Pose, PoseArray
    from sensor_msgs.msg import PointCloud2

    node = start("detector", argv)
    metrics = Metrics("detector")
    loss = LossCounter()
    settings = DetectorSettings(min_height=args.min_height, max_height=args.max_height)
    latest: dict[str, Any] = {"stamp": None, "people": []}
    publisher = node.create_publisher(PoseArray, "people", reliable(10))

    def on_cloud(message: PointCloud2, info: Any) -> None:
        loss.update(seq(info))
        begin = time.perf_counter()
        try:
            people = detect_people(cloud_xyz(message), settings)
        except ValueError as exc:
            node.get_logger().warning(f"detector: skipping a cloud: {exc}", throttle_duration_sec=10)
            return
        out = PoseArray(header=message.header)
        for person in people:
            pose = Pose()
            pose.position.x, pose.position.y = person.x, person.y
            pose.orientation.w = 1.0
            out.poses.append(pose)
        publisher.publish(out)
        stamp = stamp_ns(message.header.stamp)
        done = node.get_clock().now().nanoseconds
        latest["stamp"] = stamp / 1e9
        latest["people"] = [{"x": round(p.x, 3), "y": round(p.y, 3), "height": round(p.height, 3)} for p in people]
        metrics.report("pointcloud_processing_ms", (done - stamp) / 1e6)
        metrics.report("detection_ms", (time.perf_counter() - begin) * 1000, people=str(len(people)))
        if loss.received % 10 == 0:
            metrics.report("message_loss_pct", loss.loss_pct, topic="pointcloud_sampled")

    if args.http_port:
        detector.serve(args.http_port, latest)
    subscribe_counted(node, PointCloud2, "pointcloud_sampled", on_cloud, reliable(1))
    return spin(node, metrics)
