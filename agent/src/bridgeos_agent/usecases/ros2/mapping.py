"""Autonomous Mapping's Mapping on ROS 2: a log-odds occupancy grid from ``scan`` at the ``odom`` poses.

The same pairing and grid as the ROS 1 node; nav_msgs/OccupancyGrid on ``map`` (transient-local)
every ``--period`` seconds.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from bridgeos_agent.usecases import mapping
from bridgeos_agent.usecases.motion import Pose
from bridgeos_agent.usecases.occupancy import LogOddsMap, ScanPairing
from bridgeos_agent.usecases.ros2.node import (
    latched,
    node_args,
    reliable,
    seq,
    spin,
    stamp_ns,
    start,
    subscribe_counted,
)
from bridgeos_agent.usecases.rosio import LossCounter, Metrics, grid_message, pose_of


def main(argv: list[str]) -> int:
    args = mapping.parse_args(node_args(argv))
    from nav_msgs.msg import OccupancyGrid, Odometry
    from sensor_msgs.msg import LaserScan
    from std_msgs.msg import Header

    node = start("mapping", argv)
    metrics = Metrics("mapping")
    scans_loss, odom_loss = LossCounter(), LossCounter()
    grid = args.world.grid(args.resolution)
    built = LogOddsMap(grid)

    def fold(scan: LaserScan, pose: Pose) -> None:
        angles = scan.angle_min + np.arange(len(scan.ranges)) * scan.angle_increment
        built.integrate(pose, angles, np.asarray(scan.ranges, dtype=np.float64), scan.range_max)

    pairing: ScanPairing[Any] = ScanPairing(fold)
    publisher = node.create_publisher(OccupancyGrid, "map", latched())

    # One executor thread runs every callback: no lock needed.
    def on_scan(scan: LaserScan, info: Any) -> None:
        scans_loss.update(seq(info))
        pairing.scan(stamp_ns(scan.header.stamp), scan)

    def on_odom(message: Odometry, info: Any) -> None:
        odom_loss.update(seq(info))
        pairing.pose(stamp_ns(message.header.stamp), pose_of(message.pose.pose))

    def publish() -> None:
        header = Header(stamp=node.get_clock().now().to_msg(), frame_id="map")
        publisher.publish(grid_message(header, built.occupancy(), args.resolution, (grid.origin_x, grid.origin_y)))

    def report() -> None:
        metrics.report("message_loss_pct", scans_loss.loss_pct, topic="scan")
        metrics.report("message_loss_pct", odom_loss.loss_pct, topic="odom")
        metrics.report("scans_mapped", float(built.scans), unpaired=str(pairing.unpaired))

    subscribe_counted(node, LaserScan, "scan", on_scan, reliable(20))
    subscribe_counted(node, Odometry, "odom", on_odom, reliable(100))
    node.create_timer(args.period, publish)
    node.create_timer(args.report_period, report)
    print(f"[mapping] {grid.width}x{grid.height} cells of {args.resolution} m", flush=True)
    return spin(node, metrics)
