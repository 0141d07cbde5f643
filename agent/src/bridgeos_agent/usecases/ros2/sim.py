"""The simulated robot on ROS 2: the same body as the ROS 1 ``sim`` (``SimBody``) on ROS 2 topics.

Subscribes ``cmd_vel`` (Twist) and ``path`` (Path, transient-local); publishes ``pose``
(PoseStamped), ``wheels`` (TwistStamped) and ``scan`` (LaserScan).
"""

from __future__ import annotations

import time

import numpy as np

from bridgeos_agent.usecases import sim
from bridgeos_agent.usecases.ros2.node import latched, node_args, reliable, spin, stamp_ns, start
from bridgeos_agent.usecases.rosio import quaternion


def main(argv: list[str]) -> int:
    args = sim.parse_args(node_args(argv))
    from geometry_msgs.msg import PoseStamped, Twist, TwistStamped
    from nav_msgs.msg import Path
    from sensor_msgs.msg import LaserScan

    node = start("sim", argv)
    body = sim.SimBody(args.world, args.start, args.speed, args.beams, args.max_range)
    angles = body.angles
    pose_pub = node.create_publisher(PoseStamped, "pose", reliable(10))
    wheels_pub = node.create_publisher(TwistStamped, "wheels", reliable(50))
    scan_pub = node.create_publisher(LaserScan, "scan", reliable(5))
    scan_every = max(1, round(args.rate / args.scan_rate))
    state = {"last": node.get_clock().now().nanoseconds, "step": 0}

    def on_cmd(msg: Twist) -> None:
        body.command(msg.linear.x, msg.angular.z, time.monotonic())

    def on_path(msg: Path) -> None:
        body.follow(stamp_ns(msg.header.stamp), [(p.pose.position.x, p.pose.position.y) for p in msg.poses])

    def tick() -> None:
        now = node.get_clock().now()
        dt = (now.nanoseconds - state["last"]) / 1e9
        state["last"] = now.nanoseconds
        if dt <= 0:
            return
        v, w = body.step(dt, time.monotonic())
        moved = body.pose
        stamp = now.to_msg()
        wheels = TwistStamped()
        wheels.header.stamp, wheels.header.frame_id = stamp, "base_link"
        wheels.twist.linear.x, wheels.twist.angular.z = float(v), float(w)
        wheels_pub.publish(wheels)
        stamped = PoseStamped()
        stamped.header.stamp, stamped.header.frame_id = stamp, "map"
        stamped.pose.position.x, stamped.pose.position.y = float(moved.x), float(moved.y)
        o = stamped.pose.orientation
        o.x, o.y, o.z, o.w = quaternion(moved.theta)
        pose_pub.publish(stamped)
        step = state["step"]
        if step % scan_every == 0:
            scan = LaserScan()
            scan.header.stamp, scan.header.frame_id = stamp, "base_laser"
            scan.angle_min, scan.angle_max = float(angles[0]), float(angles[-1])
            scan.angle_increment = float(angles[1] - angles[0])
            scan.scan_time = 1.0 / args.scan_rate
            scan.range_min, scan.range_max = 0.05, float(args.max_range)
            scan.ranges = body.scan().astype(np.float32).tolist()
            scan_pub.publish(scan)
        if step % round(args.rate * 10) == 0:
            print(
                f"[sim] pose x={moved.x:.2f} y={moved.y:.2f} theta={moved.theta:.2f} collisions={body.collisions}",
                flush=True,
            )
        state["step"] = step + 1

    node.create_subscription(Twist, "cmd_vel", on_cmd, reliable(10))
    node.create_subscription(Path, "path", on_path, latched())
    node.create_timer(1.0 / args.rate, tick)
    print(f"[sim] {args.world.name} world, start {args.start}, {args.rate:g} Hz physics", flush=True)
    return spin(node)
