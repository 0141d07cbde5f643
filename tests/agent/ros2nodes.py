"""Small real rclpy nodes for the router's tests and benchmark: talker, listener, server, action, caller."""

from __future__ import annotations

import argparse
import os
import sys
import time

import rclpy
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy


def qos(args: argparse.Namespace) -> QoSProfile:
    return QoSProfile(
        depth=args.depth,
        reliability=ReliabilityPolicy.BEST_EFFORT if args.best_effort else ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL if args.latched else DurabilityPolicy.VOLATILE,
    )


def talker(node, args) -> None:
    from std_msgs.msg import String

    publisher = node.create_publisher(String, args.topic, qos(args))
    while args.wait and not publisher.get_subscription_count():
        time.sleep(0.01)
    time.sleep(args.settle)
    while args.gate and not os.path.exists(args.gate):
        time.sleep(0.01)
    start = time.monotonic()
    seq = 0
    while (args.count == 0 or seq < args.count) and not (args.duration and time.monotonic() - start > args.duration):
        seq += 1
        publisher.publish(String(data=f"{args.tag} {seq} {time.time():.6f}"))
        if args.rate:
            delay = start + seq / args.rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
    print(f"sent {seq}", flush=True)
    time.sleep(args.linger)


def listener(node, args) -> None:
    from std_msgs.msg import String

    def heard(message: String) -> None:
        tag, seq, stamp = message.data.split(" ")[:3]
        print(f"{tag} {seq} {(time.time() - float(stamp)) * 1000:.3f}", flush=True)

    node.create_subscription(String, args.topic, heard, qos(args))
    print("ready", flush=True)
    rclpy.spin(node)


def server(node, args) -> None:
    from std_srvs.srv import Trigger

    def answer(request, response):
        time.sleep(args.delay)
        response.success, response.message = True, args.tag
        return response

    node.create_service(Trigger, args.topic, answer)
    print("ready", flush=True)
    rclpy.spin(node)


def action(node, args) -> None:
    from rclpy.action import ActionServer
    from test_msgs.action import Fibonacci

    def execute(goal):
        feedback = Fibonacci.Feedback()
        sequence = [0, 1]
        for _ in range(goal.request.order):
            sequence.append(sequence[-1] + sequence[-2])
            feedback.sequence = sequence
            goal.publish_feedback(feedback)
            time.sleep(0.05)
        goal.succeed()
        return Fibonacci.Result(sequence=sequence)

    ActionServer(node, Fibonacci, args.topic, execute)
    print("ready", flush=True)
    rclpy.spin(node)


def caller(node, args) -> None:
    """Call a std_srvs/SetBool service once (data: true) and print its answer."""
    from std_srvs.srv import SetBool

    client = node.create_client(SetBool, args.topic)
    if not client.wait_for_service(timeout_sec=20):
        print("no service", flush=True)
        return
    future = client.call_async(SetBool.Request(data=True))
    rclpy.spin_until_future_complete(node, future, timeout_sec=20)
    answer = future.result()
    print(f"answer {answer.success} {answer.message}" if answer is not None else "no answer", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("role", choices=["talker", "listener", "server", "action", "caller"])
    parser.add_argument("--topic", default="chatter")
    parser.add_argument("--tag", default="t")
    parser.add_argument("--rate", type=float, default=10.0)
    parser.add_argument("--count", type=int, default=0)
    parser.add_argument("--depth", type=int, default=10000)
    parser.add_argument("--best-effort", action="store_true")
    parser.add_argument("--latched", action="store_true")
    parser.add_argument("--duration", type=float, default=0.0)
    parser.add_argument("--wait", action="store_true")
    parser.add_argument("--settle", type=float, default=0.0)
    parser.add_argument("--linger", type=float, default=30.0)
    parser.add_argument("--delay", type=float, default=0.0, help="a server answers after this many seconds")
    parser.add_argument("--gate", default="", help="publish only once this file exists")
    args, ros_args = parser.parse_known_args()
    rclpy.init(args=[sys.argv[0], *ros_args])
    node = rclpy.create_node(f"{args.role}_{args.tag}")
    try:
        globals()[args.role](node, args)
    except KeyboardInterrupt:
        pass


if __name__ == "__main__":
    main()
