"""Run one use-case node: ``python3 -m bridgeos_agent.usecases NODE [ARGS]`` (under the ROS python)."""

from __future__ import annotations

import importlib
import os
import re
import sys

from bridgeos_agent.usecases import NODES


def default_namespace(env: dict[str, str]) -> str | None:
    """Return the namespace a node takes when no Skill Router gave it one, or None to leave it be.

    An agent without a router still says which robot and Skill a component belongs to: keep each
    Skill's topics under ``/bridgeos/ROBOT/SKILL`` so robots and Skills sharing a master stay apart.
    """
    if env.get("ROS_NAMESPACE") or not env.get("BRIDGEOS_SKILL"):
        return None
    parts = ("bridgeos", env.get("BRIDGEOS_ROBOT") or "robot", env["BRIDGEOS_SKILL"])
    return "/" + "/".join(re.sub(r"[^A-Za-z0-9_]", "_", part) for part in parts)


def main(argv: list[str] | None = None) -> int:
    """Start the node named first on the command line with the rest of it."""
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] in ("-h", "--help") or args[0] not in NODES:
        known = ", ".join(NODES)
        print(f"usage: bridgeos-usecase NODE [ARGS]   (NODE: {known})", file=sys.stderr)
        return 0 if args and args[0] in ("-h", "--help") else 2
    namespace = default_namespace(dict(os.environ))
    if namespace:
        os.environ["ROS_NAMESPACE"] = namespace  # before rospy is imported: it reads it once, at import
    module = importlib.import_module(f"bridgeos_agent.usecases.{NODES[args[0]]}")
    return int(module.main(args[1:]) or 0)


if __name__ == "__main__":
    sys.exit(main())
