"""A real rclpy node for the bridges' tests: a test_msgs/action/Fibonacci server, parameters, a simulated clock.

A goal of order n is worked for n steps of --step seconds, each step publishing the sequence so far
as feedback. A negative order is rejected, an order of --abort-at or more is aborted half-way. It
prints what it does ("ready", "goal N", "canceled N", "succeeded N", "aborted N", "rejected N").
With --params it declares parameters of every kind (and refuses a negative 'count'); with --clock
it publishes /clock (rosgraph_msgs/Clock) from 1000 s on, 10 ms of simulated time every 10 ms.
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
    parser.add_argument("--params", action="store_true")
    parser.add_argument("--clock", action="store_true")
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
    if args.params:
        declare_parameters(node)
    if args.clock:
        publish_clock(node)
    executor = MultiThreadedExecutor(num_threads=4)
    executor.add_node(node)
    print("ready", flush=True)
    try:
        executor.spin()
    except KeyboardInterrupt:
        pass


def declare_parameters(node: Any) -> None:
    from rcl_interfaces.msg import SetParametersResult

    node.declare_parameter("gain", 2.5)
    node.declare_parameter("count", 3)
    node.declare_parameter("label", "robot")
    node.declare_parameter("enabled", True)
    node.declare_parameter("limits", [1.0, 2.0])
    node.declare_parameter("tags", ["a", "b"])
    node.declare_parameter("blob", [b"\x01", b"\x02"])

    def check(parameters: list[Any]) -> SetParametersResult:
        for parameter in parameters:
            if parameter.name == "count" and parameter.value < 0:
                return SetParametersResult(successful=False, reason="count must not be negative")
        return SetParametersResult(successful=True)

    node.add_on_set_parameters_callback(check)


def publish_clock(node: Any) -> None:
    from rosgraph_msgs.msg import Clock

    publisher = node.create_publisher(Clock, "/clock", 10)
    ticks = [0]

    def tick() -> None:
        ticks[0] += 1
        nanoseconds = 1000 * 10**9 + ticks[0] * 10**7
        message = Clock()
        message.clock.sec, message.clock.nanosec = divmod(nanoseconds, 10**9)
        publisher.publish(message)

    node.create_timer(0.01, tick)


if __name__ == "__main__":
    main()
