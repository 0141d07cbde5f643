"""Run one use-case node: ``python3 -m bridgeos_agent.usecases NODE [ARGS]`` (under the ROS python)."""

from __future__ import annotations

import importlib
import sys

from bridgeos_agent.usecases import NODES


def main(argv: list[str] | None = None) -> int:
    """Start the node named first on the command line with the rest of it."""
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] in ("-h", "--help") or args[0] not in NODES:
        known = ", ".join(NODES)
        print(f"usage: bridgeos-usecase NODE [ARGS]   (NODE: {known})", file=sys.stderr)
        return 0 if args and args[0] in ("-h", "--help") else 2
    module = importlib.import_module(f"bridgeos_agent.usecases.{NODES[args[0]]}")
    return int(module.main(args[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
