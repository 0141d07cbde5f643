"""Autonomous Mapping's Odometry on ROS 2: integrate the robot's ``wheels`` into ``odom`` (same stamp)."""

from __future__ import annotations

from typing import Any

from bridgeos_agent.usecases import odometry
from bridgeos_agent.usecases.motion import WheelOdometry
from bridgeos_agent.usecases.ros2.node import node_args, reliable, seq, spin, stamp_ns, start, subscribe_counted
from bridgeos_agent.usecases.rosio import LossCounter, Metrics, quaternion


def main(argv: list[str]) -> int:
    args = odometry.parse_args(node_args(argv))
    from geometry_msgs.msg import TwistStamped
    from nav_msgs.msg import Odometry

    node = start("odometry", argv)
    metrics = Metrics("odometry")
    loss = LossCounter()
    publisher = node.create_publisher(Odometry, "odom", reliable(50))
    wheel_odometry = WheelOdometry(args.start)

    def on_wheels(message: TwistStamped, info: Any) -> None:
        loss.update(seq(info))
        v, w = message.twist.linear.x, message.twist.angular.z
        pose = wheel_odometry.update(stamp_ns(message.header.stamp), v, w)
        odom = Odometry()
        odom.header.stamp = message.header.stamp
        odom.header.frame_id, odom.child_frame_id = "odom", "base_link"
        odom.pose.pose.position.x, odom.pose.pose.position.y = float(pose.x), float(pose.y)
        o = odom.pose.pose.orientation
        o.x, o.y, o.z, o.w = quaternion(pose.theta)
        odom.twist.twist.linear.x, odom.twist.twist.angular.z = v, w
        publisher.publish(odom)
        if loss.received % 200 == 0:
            metrics.report("message_loss_pct", loss.loss_pct, topic="wheels")

    subscribe_counted(node, TwistStamped, "wheels", on_wheels, reliable(100))
    print(f"[odometry] starting at {args.start}", flush=True)
    return spin(node, metrics)
