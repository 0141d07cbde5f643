"""Autonomous Navigation's Robot Mover on ROS 2: send the tour's goals one after the other on ``goal``.

A goal is reached within ``--tolerance`` of ``pose`` and re-sent every ``--repeat`` seconds until
then; ``tour_duration_s`` per tour, as the ROS 1 node.
"""

from __future__ import annotations

import math
import time
from typing import Any

from bridgeos_agent.usecases import mover
from bridgeos_agent.usecases.ros2.node import node_args, reliable, seq, spin, start, subscribe_counted
from bridgeos_agent.usecases.rosio import LossCounter, Metrics


def main(argv: list[str]) -> int:
    args = mover.parse_args(node_args(argv))
    from geometry_msgs.msg import PoseStamped

    node = start("mover", argv)
    metrics = Metrics("mover")
    loss = LossCounter()
    publisher = node.create_publisher(PoseStamped, "goal", reliable(5))
    state: dict[str, Any] = {"pose": None, "index": 0, "goal": None, "sent": -math.inf, "started": None, "tours": 0}

    def on_pose(message: PoseStamped, info: Any) -> None:
        loss.update(seq(info))
        state["pose"] = (message.pose.position.x, message.pose.position.y)

    def tick() -> None:
        if state["pose"] is None or (args.loops and state["tours"] >= args.loops):
            return
        if state["started"] is None:
            state["started"] = time.monotonic()
        index = state["index"]
        gx, gy = args.goals[index]
        if math.dist(state["pose"], (gx, gy)) <= args.tolerance:
            print(f"[mover] reached goal {index + 1} ({gx}, {gy})", flush=True)
            state["index"], state["goal"], state["sent"] = index + 1, None, -math.inf
            if state["index"] == len(args.goals):
                state["tours"] += 1
                metrics.report("tour_duration_s", time.monotonic() - state["started"], tour=str(state["tours"]))
                metrics.report("message_loss_pct", loss.loss_pct, topic="pose")
                state["index"], state["started"] = 0, None
                if args.loops and state["tours"] >= args.loops:
                    print(f"[mover] done: {state['tours']} tours", flush=True)
            return
        if state["goal"] is None:
            goal = PoseStamped()
            goal.header.stamp = node.get_clock().now().to_msg()  # one stamp per goal: the planner's key
            goal.header.frame_id = "map"
            goal.pose.position.x, goal.pose.position.y = float(gx), float(gy)
            goal.pose.orientation.w = 1.0
            state["goal"] = goal
        if time.monotonic() - state["sent"] >= args.repeat:
            publisher.publish(state["goal"])
            state["sent"] = time.monotonic()

    subscribe_counted(node, PoseStamped, "pose", on_pose, reliable(10))
    node.create_timer(0.1, tick)
    print(f"[mover] tour of {len(args.goals)} goals", flush=True)
    return spin(node, metrics)
