"""Real rospy nodes for the Skill Router's tests and benchmark, run by Debian's /usr/bin/python3.

Kept free of anything but the standard library and rospy: the venv's interpreter cannot
import rospy, so the tests start these as subprocesses. Each node lives in the namespace
its ``ROS_NAMESPACE`` gives it, exactly like a Skill component.

    talker   --topic chatter --tag robot [--rate 1000] [--count N] [--size 0]
    listener --topic chatter                       prints "tag seq" per message, one a line
    server   --service trigger --tag robot         std_srvs/Trigger answering with its tag
    pairs    --pairs 10 --rate 100 --seconds 5 --mode pub|sub --prefix /bench   (benchmark; rate 0: flat out)
    component --inputs a,b [--topic out --rate 20 --size 1000]   subscribes to inputs, publishes its output
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time


def talker(args: argparse.Namespace) -> None:
    """Publish "tag seq time padding" strings at a fixed rate."""
    import rospy
    from std_msgs.msg import String

    rospy.init_node(f"talker_{args.tag}", anonymous=True, disable_signals=True)
    pub = rospy.Publisher(args.topic, String, queue_size=None)  # synchronous: nothing dropped here
    deadline = time.monotonic() + 60
    while args.wait and pub.get_num_connections() == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    print("ready", flush=True)
    padding = "x" * args.size
    period = 1.0 / args.rate
    seq = 0
    next_at = time.monotonic()
    while not rospy.is_shutdown() and (args.count == 0 or seq < args.count):
        seq += 1
        pub.publish(String(data=f"{args.tag} {seq} {time.time():.6f} {padding}"))
        next_at += period
        delay = next_at - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -0.5:
            next_at = time.monotonic()  # far behind (a loaded machine): do not burst to catch up
    print(f"sent {seq}", flush=True)
    time.sleep(args.linger)


def listener(args: argparse.Namespace) -> None:
    """Print the tag and sequence number of every message received."""
    import rospy
    from std_msgs.msg import String

    lock = threading.Lock()

    def received(msg: String) -> None:
        tag, seq = msg.data.split(" ", 2)[:2]
        with lock:
            sys.stdout.write(f"{tag} {seq}\n")
            sys.stdout.flush()

    rospy.init_node("listener", anonymous=True, disable_signals=True)
    rospy.Subscriber(args.topic, String, received, queue_size=None)
    print("ready", flush=True)
    rospy.spin()


def server(args: argparse.Namespace) -> None:
    """Answer std_srvs/Trigger calls with this instance's tag."""
    import rospy
    from std_srvs.srv import Trigger, TriggerResponse

    rospy.init_node(f"server_{args.tag}", anonymous=True, disable_signals=True)
    rospy.Service(args.service, Trigger, lambda _: TriggerResponse(success=True, message=args.tag))
    print("ready", flush=True)
    rospy.spin()


def pairs(args: argparse.Namespace) -> None:
    """Run the publishers or the subscribers of N pairs; subscribers print a JSON summary."""
    import rospy
    from std_msgs.msg import String

    rospy.init_node(f"bench_{args.mode}", anonymous=True, disable_signals=True)
    names = [f"{args.prefix}{n}/data" for n in range(args.pairs)]
    if args.mode == "pub":
        pubs = [rospy.Publisher(name, String, queue_size=None) for name in names]
        deadline = time.monotonic() + 120
        while any(p.get_num_connections() == 0 for p in pubs) and time.monotonic() < deadline:
            time.sleep(0.01)
        print("ready", flush=True)
        sys.stdin.readline()  # the benchmark says when every subscriber is connected
        period = 1.0 / args.rate if args.rate > 0 else 0.0  # 0: as fast as the subscribers take them
        end = time.monotonic() + args.seconds
        next_at = time.monotonic()
        sent = 0
        while time.monotonic() < end:
            for pub in pubs:
                pub.publish(String(data=f"{time.time():.6f} {sent}"))
                sent += 1
            if period:
                next_at += period
                delay = next_at - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
        print(json.dumps({"sent": sent}), flush=True)
        time.sleep(args.linger)
        return
    lock = threading.Lock()
    stats = {"received": 0, "latencies": []}

    def received(msg: String) -> None:
        now = time.time()
        latency = now - float(msg.data.split(" ", 1)[0])
        with lock:
            stats["received"] += 1
            if stats["received"] % args.sample == 0:
                stats["latencies"].append(latency)

    for name in names:
        rospy.Subscriber(name, String, received, queue_size=None)
    print("ready", flush=True)
    sys.stdin.readline()  # the benchmark says when publishing is over
    with lock:
        print(json.dumps(stats), flush=True)


def component(args: argparse.Namespace) -> None:
    """Subscribe to a Skill component's inputs and publish its output (padding of --size) at --rate."""
    import rospy
    from std_msgs.msg import String

    rospy.init_node(f"component_{args.tag}", anonymous=True, disable_signals=True)
    counts = {}
    for name in filter(None, args.inputs.split(",")):
        counts[name] = 0

        def received(msg: String, name: str = name) -> None:
            counts[name] += 1

        rospy.Subscriber(name, String, received, queue_size=None)
    pub = rospy.Publisher(args.topic, String, queue_size=None) if args.publish else None
    print("ready", flush=True)
    padding = "x" * args.size
    period = 1.0 / args.rate
    seq = 0
    next_at = time.monotonic()
    while not rospy.is_shutdown():
        if pub is not None:
            seq += 1
            pub.publish(String(data=f"{args.tag} {seq} {time.time():.6f} {padding}"))
        next_at += period
        delay = next_at - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        elif delay < -0.5:
            next_at = time.monotonic()


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("role", choices=["talker", "listener", "server", "pairs", "component"])
    parser.add_argument("--topic", default="chatter")
    parser.add_argument("--service", default="trigger")
    parser.add_argument("--tag", default="robot")
    parser.add_argument("--rate", type=float, default=100.0)
    parser.add_argument("--count", type=int, default=0)
    parser.add_argument("--size", type=int, default=0)
    parser.add_argument("--wait", action="store_true", help="publish only once a subscriber is connected")
    parser.add_argument("--linger", type=float, default=1.0)
    parser.add_argument("--pairs", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--mode", choices=["pub", "sub"], default="pub")
    parser.add_argument("--prefix", default="/bench")
    parser.add_argument("--sample", type=int, default=1)
    parser.add_argument("--inputs", default="", help="component: topics to subscribe, comma-separated")
    parser.add_argument("--publish", action="store_true", help="component: publish --topic")
    args = parser.parse_args()
    roles = {"talker": talker, "listener": listener, "server": server, "pairs": pairs, "component": component}
    roles[args.role](args)


if __name__ == "__main__":
    main()
