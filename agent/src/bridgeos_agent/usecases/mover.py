"""Autonomous Navigation's Robot Mover: send the tour's goals one after the other on ``goal``.

Watches ``pose``; a goal is reached within ``--tolerance``; each goal is re-sent every
``--repeat`` seconds until then (a lost message only delays the tour). Reports
``tour_duration_s`` for each tour, the thesis's "time needed for completing a map tour".
"""

from __future__ import annotations

import argparse
import math
import time

from bridgeos_agent.usecases.world import get_world


def parse_points(text: str) -> list[tuple[float, float]]:
    """Parse 'x,y;x,y' into points."""
    points = []
    for part in filter(None, (p.strip() for p in text.split(";"))):
        try:
            x, y = (float(v) for v in part.split(","))
        except ValueError:
            raise ValueError(f"a point is 'x,y' in metres, not {part!r}") from None
        points.append((x, y))
    if not points:
        raise ValueError("need at least one point")
    return points


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="bridgeos-usecase mover", description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office", help="world whose tour to drive (office, room)")
    parser.add_argument("--goals", default=None, help="goals as 'x,y;x,y' (default: the world's tour)")
    parser.add_argument("--tolerance", type=float, default=0.25, help="metres from a goal that count as there")
    parser.add_argument("--repeat", type=float, default=3.0, help="seconds between re-sends of a goal")
    parser.add_argument("--loops", type=int, default=0, help="tours to drive (0: forever)")
    args = parser.parse_args(argv)
    if not (0.05 <= args.tolerance <= 5 and 0.5 <= args.repeat <= 600 and args.loops >= 0):
        parser.error("need 0.05 <= --tolerance <= 5, 0.5 <= --repeat <= 600 and --loops >= 0")
    try:
        args.goals = parse_points(args.goals) if args.goals is not None else list(get_world(args.world).goals)
    except ValueError as exc:
        parser.error(str(exc))
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    import rospy
    from geometry_msgs.msg import PoseStamped

    from bridgeos_agent.usecases.rosio import LossCounter, Metrics

    rospy.init_node("mover")
    metrics = Metrics("mover")
    loss = LossCounter()
    publisher = rospy.Publisher("goal", PoseStamped, queue_size=5)
    state: dict = {"pose": None}

    def on_pose(message: PoseStamped) -> None:
        loss.update(message.header.seq)
        state["pose"] = (message.pose.position.x, message.pose.position.y)

    rospy.Subscriber("pose", PoseStamped, on_pose, queue_size=10)
    print(f"[mover] tour of {len(args.goals)} goals", flush=True)
    tours = 0
    rate = rospy.Rate(10)
    try:
        while not rospy.is_shutdown() and (args.loops == 0 or tours < args.loops):
            while state["pose"] is None and not rospy.is_shutdown():
                rate.sleep()
            started = time.monotonic()
            for index, (gx, gy) in enumerate(args.goals):
                goal = PoseStamped()
                goal.header.stamp = rospy.Time.now()
                goal.header.frame_id = "map"
                goal.pose.position.x, goal.pose.position.y = gx, gy
                goal.pose.orientation.w = 1.0
                sent = -math.inf
                while not rospy.is_shutdown():
                    if math.dist(state["pose"], (gx, gy)) <= args.tolerance:
                        print(f"[mover] reached goal {index + 1} ({gx}, {gy})", flush=True)
                        break
                    if time.monotonic() - sent >= args.repeat:
                        publisher.publish(goal)
                        sent = time.monotonic()
                    rate.sleep()
            if rospy.is_shutdown():
                break
            tours += 1
            metrics.report("tour_duration_s", time.monotonic() - started, tour=str(tours))
            metrics.report("message_loss_pct", loss.loss_pct, topic="pose")
        print(f"[mover] done: {tours} tours", flush=True)
        if not rospy.is_shutdown():
            rospy.spin()
    except rospy.ROSInterruptException:
        pass
    finally:
        metrics.close()
    return 0
