"""Autonomous Mapping's Robot Controller: drive the predefined route with ``cmd_vel`` from ``odom``.

Publishes geometry_msgs/Twist at 10 Hz, steering by the odometry's pose along the world's
route (there and back again on every other tour). Reports ``tour_duration_s`` per tour.
"""

from __future__ import annotations

import argparse
import time

from bridgeos_agent.usecases.mover import parse_points
from bridgeos_agent.usecases.world import get_world


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="bridgeos-usecase controller", description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office", help="world whose route to drive (office, room)")
    parser.add_argument("--route", default=None, help="waypoints as 'x,y;x,y' (default: the world's route)")
    parser.add_argument("--speed", type=float, default=0.5, help="top speed, m/s")
    parser.add_argument("--loops", type=int, default=0, help="tours to drive (0: forever)")
    args = parser.parse_args(argv)
    if not (0 < args.speed <= 5 and args.loops >= 0):
        parser.error("need 0 < --speed <= 5 and --loops >= 0")
    try:
        args.route = parse_points(args.route) if args.route is not None else list(get_world(args.world).route)
    except ValueError as exc:
        parser.error(str(exc))
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    import rospy
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry

    from bridgeos_agent.usecases.motion import Follower
    from bridgeos_agent.usecases.rosio import LossCounter, Metrics, pose_of

    rospy.init_node("controller")
    metrics = Metrics("controller")
    loss = LossCounter()
    publisher = rospy.Publisher("cmd_vel", Twist, queue_size=10)
    state: dict = {"pose": None}

    def on_odom(message: Odometry) -> None:
        loss.update(message.header.seq)
        state["pose"] = pose_of(message.pose.pose)

    rospy.Subscriber("odom", Odometry, on_odom, queue_size=20)
    print(f"[controller] route of {len(args.route)} waypoints at {args.speed} m/s", flush=True)
    rate = rospy.Rate(10)
    tours = 0
    route = list(args.route)
    try:
        while not rospy.is_shutdown() and (args.loops == 0 or tours < args.loops):
            while state["pose"] is None and not rospy.is_shutdown():
                rate.sleep()
            follower = Follower(route, max_speed=args.speed)
            started = time.monotonic()
            while not rospy.is_shutdown() and not follower.done:
                v, w = follower.command(state["pose"])
                command = Twist()
                command.linear.x, command.angular.z = v, w
                publisher.publish(command)
                rate.sleep()
            if rospy.is_shutdown():
                break
            publisher.publish(Twist())
            tours += 1
            metrics.report("tour_duration_s", time.monotonic() - started, tour=str(tours))
            metrics.report("message_loss_pct", loss.loss_pct, topic="odom")
            route.reverse()  # back the way it came
        print(f"[controller] done: {tours} tours", flush=True)
        if not rospy.is_shutdown():
            rospy.spin()
    except rospy.ROSInterruptException:
        pass
    finally:
        metrics.close()
    return 0
