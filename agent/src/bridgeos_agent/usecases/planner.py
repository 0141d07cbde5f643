"""Autonomous Navigation's Path Planner (cloud only): A* from ``pose`` to each ``goal`` on ``map``.

Publishes nav_msgs/Path on ``path`` stamped with its goal's stamp, so a goal sent again
gets the same plan again (not a new one) and the robot keeps driving.
"""

from __future__ import annotations

import argparse
import threading


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="bridgeos-usecase planner", description=__doc__.splitlines()[0])
    parser.add_argument("--robot-radius", type=float, default=0.25, help="clearance kept from obstacles, metres")
    args = parser.parse_args(argv)
    if not 0 <= args.robot_radius <= 2:
        parser.error("--robot-radius must be 0-2 m")
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    import rospy
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import OccupancyGrid, Path
    from std_msgs.msg import Header

    from bridgeos_agent.usecases.planning import GoalPlanner
    from bridgeos_agent.usecases.rosio import LossCounter, Metrics, grid_from_message
    from bridgeos_agent.usecases.world import Grid

    rospy.init_node("planner")
    metrics = Metrics("planner")
    loss = LossCounter()
    planner = GoalPlanner(args.robot_radius)
    state: dict = {"goal": None, "path": None}
    # Latched: a subscriber that connects late (or a migrated one) still gets the current plan.
    publisher = rospy.Publisher("path", Path, queue_size=5, latch=True)

    lock = threading.Lock()  # rospy runs each subscription's callbacks on a thread of its own

    def plan() -> None:
        with lock:
            result = planner.plan()
            if result is None:
                return
            if not result.fresh:
                publisher.publish(state["path"])  # the goal again: the same plan again
                return
            goal = state["goal"]
            path = Path(header=Header(stamp=goal.header.stamp, frame_id="map"))
            for x, y in result.points or []:
                step = PoseStamped(header=path.header)
                step.pose.position.x, step.pose.position.y = x, y
                step.pose.orientation.w = 1.0
                path.poses.append(step)
            state["path"] = path
            publisher.publish(path)
            if result.points is None:
                print(f"[planner] no path from {planner.position} to {planner.goal}", flush=True)
            metrics.report("planning_ms", result.elapsed_ms, waypoints=str(len(path.poses)))

    def on_map(message: OccupancyGrid) -> None:
        values, resolution, origin = grid_from_message(message)
        with lock:
            planner.set_map(values, Grid(resolution, origin[0], origin[1], values.shape[1], values.shape[0]))
        plan()

    def on_pose(message: PoseStamped) -> None:
        loss.update(message.header.seq)
        with lock:
            waiting = planner.set_position(message.pose.position.x, message.pose.position.y)
        if waiting:
            plan()  # a goal came before the robot's first pose
        if loss.received % 200 == 0:
            metrics.report("message_loss_pct", loss.loss_pct, topic="pose")

    def on_goal(message: PoseStamped) -> None:
        with lock:
            state["goal"] = message
            planner.set_goal(message.header.stamp.to_nsec(), message.pose.position.x, message.pose.position.y)
        plan()

    rospy.Subscriber("map", OccupancyGrid, on_map, queue_size=1)
    rospy.Subscriber("pose", PoseStamped, on_pose, queue_size=10)
    rospy.Subscriber("goal", PoseStamped, on_goal, queue_size=10)
    print("[planner] waiting for map, pose and goals", flush=True)
    try:
        rospy.spin()
    finally:
        metrics.close()
    return 0
