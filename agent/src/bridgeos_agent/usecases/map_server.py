"""Autonomous Navigation's Map Server: publish the known map of a world on ``map``.

nav_msgs/OccupancyGrid (0 free, 100 occupied), latched and re-sent every ``--period``
seconds so a planner that starts, moves or lost a message gets it again.
"""

from __future__ import annotations

import argparse

from bridgeos_agent.usecases.world import get_world


def parse_args(argv: list[str]) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="bridgeos-usecase map-server", description=__doc__.splitlines()[0])
    parser.add_argument("--world", default="office", help="world whose map to serve (office, room)")
    parser.add_argument("--resolution", type=float, default=0.1, help="metres a cell")
    parser.add_argument("--period", type=float, default=5.0, help="seconds between re-sends")
    args = parser.parse_args(argv)
    if not (0.02 <= args.resolution <= 1 and 0.1 <= args.period <= 3600):
        parser.error("need 0.02 <= --resolution <= 1 and 0.1 <= --period <= 3600")
    try:
        args.world = get_world(args.world)
    except ValueError as exc:
        parser.error(str(exc))
    return args


def main(argv: list[str]) -> int:
    args = parse_args(argv)
    import numpy as np
    import rospy
    from nav_msgs.msg import OccupancyGrid
    from std_msgs.msg import Header

    from bridgeos_agent.usecases.rosio import grid_message

    rospy.init_node("map_server")
    grid = args.world.grid(args.resolution)
    values = np.where(args.world.occupancy(args.resolution), 100, 0).astype(np.int8)
    publisher = rospy.Publisher("map", OccupancyGrid, queue_size=1, latch=True)
    print(f"[map_server] {args.world.name}: {grid.width}x{grid.height} cells of {args.resolution} m", flush=True)
    rate = rospy.Rate(1.0 / args.period)
    try:
        while not rospy.is_shutdown():
            publisher.publish(
                grid_message(Header(stamp=rospy.Time.now(), frame_id="map"), values, args.resolution, (0, 0))
            )
            rate.sleep()
    except rospy.ROSInterruptException:
        pass
    return 0
