"""The thesis's three use-case Skills (§5.3, Table 5.1) as real ROS nodes, and their simulated robot.

Every node runs under the ROS python (Debian's ``/usr/bin/python3`` with rospy and numpy),
on the host with the process runtime or in the ``bridgeos/ros:noetic`` image, so nothing in
this package imports anything the agent's venv alone has. ``bridgeos-usecase NODE [ARGS]``
starts one node (see :data:`NODES`); topic names are relative, so a node lands in the
``ROS_NAMESPACE`` the Skill Router gives its instance.
"""

from __future__ import annotations

__all__ = ["NODES"]

# Node name (as on the command line) -> module of this package that runs it.
NODES = {
    # simulated robot: kinematics, laser, wheel encoders, path following
    "sim": "sim",
    # People Detection
    "pointcloud": "pointcloud",
    "sampler": "sampler",
    "detector": "detector",
    # Autonomous Navigation
    "map-server": "map_server",
    "planner": "planner",
    "mover": "mover",
    # Autonomous Mapping
    "controller": "controller",
    "mapping": "mapping",
    "odometry": "odometry",
}
