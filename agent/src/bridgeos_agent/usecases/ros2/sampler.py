"""People Detection's Sampling on ROS 2: thin each ``pointcloud`` with a voxel grid into ``pointcloud_sampled``."""

from __future__ import annotations

import time
from typing import Any

from bridgeos_agent.usecases import sampler
from bridgeos_agent.usecases.detection import voxel_sample
from bridgeos_agent.usecases.ros2.node import node_args, reliable, seq, spin, start, subscribe_counted
from bridgeos_agent.usecases.rosio import XYZ_DTYPE, LossCounter, Metrics, cloud_message, cloud_xyz


def main(argv: list[str]) -> int:
    args = sampler.parse_args(node_args(argv))
    from sensor_msgs.msg import PointCloud2

    node = start("sampler", argv)
    metrics = Metrics("sampler")
    loss = LossCounter()
    publisher = node.create_publisher(PointCloud2, "pointcloud_sampled", reliable(1))

    def on_cloud(message: PointCloud2, info: Any) -> None:
        begin = time.perf_counter()
        loss.update(seq(info))
        try:
            sampled = voxel_sample(cloud_xyz(message), args.voxel, args.max_range)
        except ValueError as exc:
            node.get_logger().warning(f"sampler: skipping a cloud: {exc}", throttle_duration_sec=10)
            return
        publisher.publish(cloud_message(message.header, sampled.view(XYZ_DTYPE).reshape(-1)))
        metrics.report("sampling_ms", (time.perf_counter() - begin) * 1000, points=str(len(sampled)))
        if loss.received % 10 == 0:
            metrics.report("message_loss_pct", loss.loss_pct, topic="pointcloud")

    # Depth 1: a sampler that falls behind drops stale clouds, as ROS 1's queue_size=1 does.
    subscribe_counted(node, PointCloud2, "pointcloud", on_cloud, reliable(1))
    print(f"[sampler] voxel {args.voxel} m", flush=True)
    return spin(node, metrics)
