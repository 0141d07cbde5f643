"""Autonomous Mapping's Robot Controller on ROS 2: drive the route with ``cmd_vel`` from ``odom`` (10 Hz).

Pure pursuit (``Follower``) along the world's route, back again on every other tour;
``tour_duration_s`` per tour, as the ROS 1 node.
"""

from __future__ import annotations

import time
from typing import Any

from bridgeos_agent.usecases import controller
from bridgeos_agent.usecases.motion import Follower
from bridgeos_agent.usecases.ros2.node import node_args, reliable, seq, spin, start, subscribe_counted
from bridgeos_agent.usecases.rosio import LossCounter, Metrics, pose_of


def main(argv: list[str]) -> int:
    args = controller.parse_args(node_args(argv))
    from geometry_msgs.msg import Twist
    from nav_msgs.msg import Odometry

    node = start("controller", argv)
    metrics = Metrics("controller")
    loss = LossCounter()
    publisher = node.create_publisher(Twist, "cmd_vel", reliable(10))
    route = list(args.route)
    state: dict[str, Any] = {"pose": None, "follower": None, "started": 0.0, "tours": 0}

    def on_odom(message: Odometry, info: Any) -> None:
        loss.update(seq(info))
        state["pose"] = pose_of(message.pose.pose)

    def tick() -> None:
        if state["pose"] is None or (args.loops and state["tours"] >= args.loops):
            return
        follower = state["follower"]
        if follower is None:
            follower = state["follower"] = Follower(list(route), max_speed=args.speed)
            state["started"] = time.monotonic()
        if not follower.done:
            v, w = follower.command(state["pose"])
            command = Twist()
            command.linear.x, command.angular.z = float(v), float(w)
            publisher.publish(command)
            return
        publisher.publish(Twist())
        state["tours"] += 1
        metrics.report("tour_duration_s", time.monotonic() - state["started"], tour=str(state["tours"]))
        metrics.report("message_loss_pct", loss.loss_pct, topic="odom")
        route.reverse()  # back the way it came
        state["follower"] = None
        if args.loops and state["tours"] >= args.loops:
            print(f"[controller] done: {state['tours']} tours", flush=True)

    subscribe_counted(node, Odometry, "odom", on_odom, reliable(20))
    node.create_timer(0.1, tick)
    print(f"[controller] route of {len(args.route)} waypoints at {args.speed} m/s", flush=True)
    return spin(node, metrics)
