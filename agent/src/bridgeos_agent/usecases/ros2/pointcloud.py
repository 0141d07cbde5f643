"""People Detection's Publisher on ROS 2: the simulated RGB-D camera publishing ``pointcloud`` (PointCloud2)."""

from __future__ import annotations

import time

from bridgeos_agent.usecases import pointcloud
from bridgeos_agent.usecases.camera import default_scene, render
from bridgeos_agent.usecases.ros2.node import node_args, reliable, spin, start
from bridgeos_agent.usecases.rosio import Metrics, cloud_message


def main(argv: list[str]) -> int:
    args = pointcloud.parse_args(node_args(argv))
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Header

    node = start("pointcloud", argv)
    metrics = Metrics("pointcloud")
    started = time.perf_counter()
    scene = default_scene(args.people)
    message = cloud_message(Header(frame_id="camera"), render(scene, args.width, args.height), height=args.height)
    megabytes = len(message.data) / 1e6
    print(
        f"[pointcloud] {args.width}x{args.height} cloud, {megabytes:.1f} MB, {len(scene.people)} people, "
        f"rendered in {time.perf_counter() - started:.2f} s, {args.rate:g} Hz",
        flush=True,
    )
    publisher = node.create_publisher(PointCloud2, "pointcloud", reliable(1))
    sent = 0

    def tick() -> None:
        nonlocal sent
        if args.count and sent >= args.count:
            return  # --count reached: stay up, as a sensor driver would
        message.header.stamp = node.get_clock().now().to_msg()
        begin = time.perf_counter()
        publisher.publish(message)
        sent += 1
        if sent % max(1, round(args.rate * 10)) == 1:
            metrics.report("pointcloud_publish_ms", (time.perf_counter() - begin) * 1000, mb=f"{megabytes:.1f}")

    node.create_timer(1.0 / args.rate, tick)
    return spin(node, metrics)
