"""Autonomous Navigation's Map Server on ROS 2: the world's known map on ``map``, transient-local, re-sent."""

from __future__ import annotations

import numpy as np

from bridgeos_agent.usecases import map_server
from bridgeos_agent.usecases.ros2.node import latched, node_args, spin, start
from bridgeos_agent.usecases.rosio import grid_message


def main(argv: list[str]) -> int:
    args = map_server.parse_args(node_args(argv))
    from nav_msgs.msg import OccupancyGrid
    from std_msgs.msg import Header

    node = start("map_server", argv)
    grid = args.world.grid(args.resolution)
    values = np.where(args.world.occupancy(args.resolution), 100, 0).astype(np.int8)
    # Transient-local (ROS 1's latch): a planner that starts or moves later still gets the map.
    publisher = node.create_publisher(OccupancyGrid, "map", latched())
    print(f"[map_server] {args.world.name}: {grid.width}x{grid.height} cells of {args.resolution} m", flush=True)

    def publish() -> None:
        header = Header(stamp=node.get_clock().now().to_msg(), frame_id="map")
        publisher.publish(grid_message(header, values, args.resolution, (0.0, 0.0)))

    publish()
    node.create_timer(args.period, publish)
    return spin(node)
