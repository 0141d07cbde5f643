"""Autonomous Mapping's Odometry: integrate the robot's ``wheels`` into ``odom``.

Each geometry_msgs/TwistStamped says at which speeds the wheels turned over the step
ending at its stamp; the unicycle model turns them into a pose, published as
nav_msgs/Odometry with the same stamp (so the mapper can pair it with the scan of that
step). A lost message is a step missed: the pose drifts, and ``message_loss_pct`` says so.
"""

from __future__ import annotations

import argparse

from bridgeos_agent.usecases.motion import Pose
from bridgeos_agent.usecases.world import get_world


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="bridgeos-usecase odometry", description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office", help="world the robot starts in (its start pose)")
    parser.add_argument("--start", default=None, help="x,y,theta the robot starts at (default: the world's)")
    args = parser.parse_args(argv)
    try:
        args.start = (
            Pose(*(float(v) for v in args.start.split(","))) if args.start else Pose(*get_world(args.world).start)
        )
    except (ValueError, TypeError) as exc:
        parser.error(f"--start/--world: {exc}")
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    import rospy
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Odometry

    from bridgeos_agent.usecases.motion import WheelOdometry
    from bridgeos_agent.usecases.rosio import LossCounter, Metrics, quaternion

    rospy.init_node("odometry")
    metrics = Metrics("odometry")
    loss = LossCounter()
    publisher = rospy.Publisher("odom", Odometry, queue_size=50)
    wheel_odometry = WheelOdometry(args.start)

    def on_wheels(message: TwistStamped) -> None:
        loss.update(message.header.seq)
        stamp = message.header.stamp
        v, w = message.twist.linear.x, message.twist.angular.z
        pose = wheel_odometry.update(stamp.to_nsec(), v, w)
        odom = Odometry()
        odom.header.stamp = stamp
        odom.header.frame_id = "odom"
        odom.child_frame_id = "base_link"
        odom.pose.pose.position.x, odom.pose.pose.position.y = pose.x, pose.y
        o = odom.pose.pose.orientation
        o.x, o.y, o.z, o.w = quaternion(pose.theta)
        odom.twist.twist.linear.x, odom.twist.twist.angular.z = v, w
        publisher.publish(odom)
        if loss.received % 200 == 0:
            metrics.report("message_loss_pct", loss.loss_pct, topic="wheels")

    rospy.Subscriber("wheels", TwistStamped, on_wheels, queue_size=100)
    print(f"[odometry] starting at {args.start}", flush=True)
    try:
        rospy.spin()
    finally:
        metrics.close()
    return 0
