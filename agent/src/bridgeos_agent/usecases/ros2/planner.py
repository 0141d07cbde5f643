"""Autonomous Navigation's Path Planner on ROS 2 (cloud only): A* from ``pose`` to each ``goal`` on ``map``.

nav_msgs/Path on ``path`` (transient-local), stamped with its goal's stamp: a goal sent again
gets the same plan again.
"""

from __future__ import annotations

from typing import Any

from bridgeos_agent.usecases import planner as ros1_planner
from bridgeos_agent.usecases.planning import GoalPlanner
from bridgeos_agent.usecases.ros2.node import (
    latched,
    node_args,
    reliable,
    seq,
    spin,
    stamp_ns,
    start,
    subscribe_counted,
)
from bridgeos_agent.usecases.rosio import LossCounter, Metrics, grid_from_message
from bridgeos_agent.usecases.world import Grid


def main(argv: list[str]) -> int:
    args = ros1_planner.parse_args(node_args(argv))
    from geometry_msgs.msg import PoseStamped
    from nav_msgs.msg import OccupancyGrid, Path
    from std_msgs.msg import Header

    node = start("planner", argv)
    metrics = Metrics("planner")
    loss = LossCounter()
    planner = GoalPlanner(args.robot_radius)
    state: dict[str, Any] = {"goal": None, "path": None}
    publisher = node.create_publisher(Path, "path", latched())

    # One executor thread runs every callback: no lock needed.
    def plan() -> None:
        result = planner.plan()
        if result is None:
            return
        if not result.fresh:
            publisher.publish(state["path"])  # the goal again: the same plan again
            return
        path = Path(header=Header(stamp=state["goal"].header.stamp, frame_id="map"))
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
        planner.set_map(values, Grid(resolution, origin[0], origin[1], values.shape[1], values.shape[0]))
        plan()

    def on_pose(message: PoseStamped, info: Any) -> None:
        loss.update(seq(info))
        if planner.set_position(message.pose.position.x, message.pose.position.y):
            plan()  # a goal came before the robot's first pose
        if loss.received % 200 == 0:
            metrics.report("message_loss_pct", loss.loss_pct, topic="pose")

    def on_goal(message: PoseStamped) -> None:
        state["goal"] = message
        planner.set_goal(stamp_ns(message.header.stamp), message.pose.position.x, message.pose.position.y)
        plan()

    node.create_subscription(OccupancyGrid, "map", on_map, latched())
    subscribe_counted(node, PoseStamped, "pose", on_pose, reliable(10))
    node.create_subscription(PoseStamped, "goal", on_goal, reliable(10))
    print("[planner] waiting for map, pose and goals", flush=True)
    return spin(node, metrics)
