"""Autonomous Mapping's Mapping: a log-odds occupancy grid from ``scan`` at the ``odom`` poses.

Pairs each sensor_msgs/LaserScan with the odometry of the same stamp (waiting a moment for
it), folds it into the grid and publishes nav_msgs/OccupancyGrid on ``map`` every
``--period`` seconds. Reports ``message_loss_pct`` of scans and odometry, and scans used.
"""

from __future__ import annotations

import argparse
import threading

from bridgeos_agent.usecases.motion import Pose
from bridgeos_agent.usecases.world import get_world


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="bridgeos-usecase mapping", description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office", help="world whose extent to map (office, room)")
    parser.add_argument("--resolution", type=float, default=0.1, help="metres a cell")
    parser.add_argument("--period", type=float, default=1.0, help="seconds between map publications")
    parser.add_argument("--report-period", type=float, default=5.0, help="seconds between metric reports")
    args = parser.parse_args(argv)
    if not (0.02 <= args.resolution <= 1 and 0.1 <= args.period <= 3600 and 0.1 <= args.report_period <= 3600):
        parser.error("need 0.02 <= --resolution <= 1 and 0.1 <= --period, --report-period <= 3600")
    try:
        args.world = get_world(args.world)
    except ValueError as exc:
        parser.error(str(exc))
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    import numpy as np
    import rospy
    from nav_msgs.msg import OccupancyGrid, Odometry
    from sensor_msgs.msg import LaserScan
    from std_msgs.msg import Header

    from bridgeos_agent.usecases.occupancy import LogOddsMap, ScanPairing
    from bridgeos_agent.usecases.rosio import LossCounter, Metrics, grid_message, pose_of

    rospy.init_node("mapping")
    metrics = Metrics("mapping")
    scans_loss, odom_loss = LossCounter(), LossCounter()
    grid = args.world.grid(args.resolution)
    built = LogOddsMap(grid)

    def fold(scan: LaserScan, pose: Pose) -> None:
        n = len(scan.ranges)
        angles = scan.angle_min + np.arange(n) * scan.angle_increment
        built.integrate(pose, angles, np.asarray(scan.ranges, dtype=np.float64), scan.range_max)

    pairing: ScanPairing[LaserScan] = ScanPairing(fold)
    publisher = rospy.Publisher("map", OccupancyGrid, queue_size=1, latch=True)
    # rospy runs each subscription's callbacks on a thread of its own.
    lock = threading.Lock()

    def on_scan(scan: LaserScan) -> None:
        with lock:
            scans_loss.update(scan.header.seq)
            pairing.scan(scan.header.stamp.to_nsec(), scan)

    def on_odom(message: Odometry) -> None:
        with lock:
            odom_loss.update(message.header.seq)
            pairing.pose(message.header.stamp.to_nsec(), pose_of(message.pose.pose))

    def publish(_event: object) -> None:
        header = Header(stamp=rospy.Time.now(), frame_id="map")
        with lock:
            values = built.occupancy()
        try:
            publisher.publish(grid_message(header, values, args.resolution, (grid.origin_x, grid.origin_y)))
        except rospy.ROSException:
            # rospy closes its publishers before its timers stop: a tick during shutdown has nowhere to go.
            if not rospy.is_shutdown():
                raise

    def report(_event: object) -> None:
        metrics.report("message_loss_pct", scans_loss.loss_pct, topic="scan")
        metrics.report("message_loss_pct", odom_loss.loss_pct, topic="odom")
        metrics.report("scans_mapped", float(built.scans), unpaired=str(pairing.unpaired))

    rospy.Subscriber("scan", LaserScan, on_scan, queue_size=20)
    rospy.Subscriber("odom", Odometry, on_odom, queue_size=100)
    timers = [
        rospy.Timer(rospy.Duration(args.period), publish),
        rospy.Timer(rospy.Duration(args.report_period), report),
    ]
    print(f"[mapping] {grid.width}x{grid.height} cells of {args.resolution} m", flush=True)
    try:
        rospy.spin()
    finally:
        for timer in timers:
            timer.shutdown()
        metrics.close()
    return 0
