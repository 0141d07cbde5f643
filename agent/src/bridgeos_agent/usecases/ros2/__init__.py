"""The three use-case Skills as ROS 2 nodes (rclpy): the same algorithms as the ROS 1 nodes, on ROS 2 topics.

They run in the agent's own Python (rclpy and the message packages come from the ``ros-jazzy-*``
wheels of ``bridgeos-agent[ros2]``): ``bridgeos-usecase2 NODE [ARGS] [--ros-args -r __ns:=NS]``.
Topic names are relative, so a node lands in the namespace the Skill Router gives its instance
(``--ros-args -r __ns:=...``, else ``ROS_NAMESPACE``); its graph comes from ``ROS_DOMAIN_ID``,
``RMW_IMPLEMENTATION`` and ``ROS_DISCOVERY_SERVER`` or ``ROS_AUTOMATIC_DISCOVERY_RANGE``. Every node
takes the arguments of its ROS 1 twin (``bridgeos-usecase``).
"""

from __future__ import annotations

from bridgeos_agent.usecases import NODES

__all__ = ["NODES"]
