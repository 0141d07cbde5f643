"""People Detection's Sampling: thin each ``pointcloud`` with a voxel grid into ``pointcloud_sampled``."""

from __future__ import annotations

import argparse
import time


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="bridgeos-usecase sampler", description=__doc__)
    parser.add_argument("--voxel", type=float, default=0.05, help="voxel edge in metres (0: only drop invalid points)")
    parser.add_argument("--range", type=float, default=12.0, dest="max_range", help="drop points farther than this")
    args = parser.parse_args(argv)
    if not (0 <= args.voxel <= 5 and 0 < args.max_range <= 100):
        parser.error("need 0 <= --voxel <= 5 and 0 < --range <= 100")
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    import rospy
    from sensor_msgs.msg import PointCloud2

    from bridgeos_agent.usecases.detection import voxel_sample
    from bridgeos_agent.usecases.rosio import BIG_BUFFER, XYZ_DTYPE, LossCounter, Metrics, cloud_message, cloud_xyz

    rospy.init_node("sampler")
    metrics = Metrics("sampler")
    loss = LossCounter()
    publisher = rospy.Publisher("pointcloud_sampled", PointCloud2, queue_size=1)

    def on_cloud(message: PointCloud2) -> None:
        begin = time.perf_counter()
        loss.update(message.header.seq)
        try:
            sampled = voxel_sample(cloud_xyz(message), args.voxel, args.max_range)
        except ValueError as exc:
            rospy.logwarn_throttle(10, f"sampler: skipping a cloud: {exc}")
            return
        publisher.publish(cloud_message(message.header, sampled.view(XYZ_DTYPE).reshape(-1)))
        metrics.report("sampling_ms", (time.perf_counter() - begin) * 1000, points=str(len(sampled)))
        if loss.received % 10 == 0:
            metrics.report("message_loss_pct", loss.loss_pct, topic="pointcloud")

    rospy.Subscriber("pointcloud", PointCloud2, on_cloud, queue_size=1, buff_size=BIG_BUFFER)
    print(f"[sampler] voxel {args.voxel} m", flush=True)
    try:
        rospy.spin()
    finally:
        metrics.close()
    return 0
