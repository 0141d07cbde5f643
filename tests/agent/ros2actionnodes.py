"""A real rclpy action server for the bridges' tests: test_msgs/action/Fibonacci, cancellable.

A goal of order n is worked for n steps of --step seconds, each step publishing the sequence so far
as feedback. A negative order is rejected, an order of --abort-at or more is aborted half-way. It
prints what it does ("ready", "goal N", "canceled N", "succeeded N", "aborted N", "rejected N").
"""

from __future__ import annotations

import argparse
import sys
import time
from typing import Any

import rclpy
from rclpy.action import ActionServer, CancelResponse, GoalResponse
from rclpy.callback_groups import ReentrantCallbackGroup
from rclpy.executors import MultiThreadedExecutor
from test_msgs.action import Fibonacci


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--action", default="fibonacci")
    parser.add_argument("--step", type=float, default=0.05)
    parser.add_argument("--abort-at", type=int, default=1000)
    parser.add_argument("--name", default="fibonacci_server")
    args, ros_args = parser.parse_known_args()
    rclpy.init(args=[sys.argv[0], *ros_args])
    node = rclpy.create_node(args.name)

    def decide(request: Fibonacci.Goal) -> GoalResponse:
        if request.order < 0:
            print(f"rejected {request.order}", flush=True)
            return GoalResponse.REJECT
        print(f"goal {request.order}", flush=True)
        return GoalResponse.ACCEPT

    def execute(goal: Any) -> Fibonacci.Result:
        order = goal.request.order
        sequence = [0, 1]
        for step in range(order):
            if goal.is_cancel_requested:
                goal.canceled()
                print(f"canceled {order}", flush=True)
                return Fibonacci.Result(sequence=sequence)
            if order >= args.abort_at and step == order // 2:
                goal.abort()
                print(f"aborted {order}", flush=True)
                return Fibonacci.Result(sequence=sequence)
            sequence.append(sequence[-1] + sequence[-2])
            goal.publish_feedback(Fibonacci.Feedback(sequence=sequence))
            time.sleep(args.step)
        goal.succeed()
        print(f"succeeded {order}", flush=True)
        return Fibonacci.Result(sequence=sequence)

    ActionServer(
        node,
        Fibonacci,
        args.action,
        execute,
        goal_callback=decide,
        cancel_callback=lambda goal: CancelResponse.ACCEPT,
        callback_group=ReentrantCallbackGroup(),
    )
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    print("ready", flush=True)
    try:
        executor.spin()
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
