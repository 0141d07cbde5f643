"""Run one ROS 2 use-case node: ``bridgeos-usecase2 NODE [ARGS] [--ros-args ...]`` (the agent's Python)."""

from __future__ import annotations

import importlib
import sys

from bridgeos_agent.usecases import NODES


def main(argv: list[str] | None = None) -> int:
    """Start the ROS 2 node named first on the command line with the rest of it."""
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] in ("-h", "--help") or args[0] not in NODES:
        known = ", ".join(NODES)
        print(f"usage: bridgeos-usecase2 NODE [ARGS] [--ros-args -r __ns:=NS]   (NODE: {known})", file=sys.stderr)
        return 0 if args and args[0] in ("-h", "--help") else 2
    from bridgeos_agent.ros2graph import rclpy_missing

    missing = rclpy_missing()
    if missing:
        print(f"bridgeos-usecase2: {missing}", file=sys.stderr)
        return 127
    module = importlib.import_module(f"bridgeos_agent.usecases.ros2.{NODES[args[0]]}")
    return int(module.main(args[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
