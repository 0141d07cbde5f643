"""``bridgeos-usecase NODE [ARGS]``: start a use-case node under the python that has rospy.

The agent's venv cannot import Debian's rospy, so from there this re-executes the ROS
python (``BRIDGEOS_ROS_PYTHON``, default ``/usr/bin/python3``) with this package appended to
its path: appended, so Debian's own numpy and rospy win over anything the venv holds.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

__all__ = ["main"]

DEFAULT_ROS_PYTHON = "/usr/bin/python3"
BOOTSTRAP = (
    "import sys; sys.path.append({path!r}); "
    "from bridgeos_agent.usecases.__main__ import main; sys.exit(main(sys.argv[1:]))"
)


def _has_ros() -> bool:
    try:
        import numpy  # noqa: F401
        import rospy  # noqa: F401
    except ImportError:
        return False
    return True


def main() -> int:
    """Run the node here if this python has rospy and numpy, else exec the ROS python with it."""
    if _has_ros():
        from bridgeos_agent.usecases.__main__ import main as run

        return run(sys.argv[1:])
    ros_python = os.environ.get("BRIDGEOS_ROS_PYTHON", DEFAULT_ROS_PYTHON)
    if not os.access(ros_python, os.X_OK):
        print(
            f"bridgeos-usecase: no ROS python at {ros_python}: install ROS 1 (Debian: ros-core python3-rospy "
            "python3-numpy) or set BRIDGEOS_ROS_PYTHON",
            file=sys.stderr,
        )
        return 127
    package_parent = str(Path(__file__).resolve().parent.parent.parent)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONHOME", "VIRTUAL_ENV")}
    env.setdefault("PYTHONUNBUFFERED", "1")
    code = BOOTSTRAP.format(path=package_parent)
    os.execve(ros_python, [ros_python, "-c", code, *sys.argv[1:]], env)
    return 127  # not reached: execve replaces this process
