"""Signals other apps follow about robots."""

from __future__ import annotations

from django.dispatch import Signal

# Sent with robot=... inside the transaction that replaced a robot's token.
credentials_rotated = Signal()

# Sent with robot_id=, config= (already normalised) whenever a robot's config is validated; a
# receiver refuses what its app cannot honour by raising ValidationError (the network app: subnets).
config_checked = Signal()

# Sent with robot_id=, reported= (the ROS master the robot reported, or None) inside the transaction
# that marks it connected; a receiver may answer the ROS master its components use (the cloud's
# orchestration: a shared one, or one of its own in the cloud). No answer: the reported one.
ros_master_wanted = Signal()

# Sent with robot_id=, graph= (the ROS 2 graph the robot reported as a dict, or None) and previous= (the
# graph kept from its last login, or None) inside the transaction
# that marks it connected; a receiver may answer the "host:port" of the discovery server the cloud runs for
# the robot's ROS 2 cloud graph (the cloud's orchestration). No answer: none.
ros2_discovery_wanted = Signal()

# Sent with robot_id=, ros_master= (the master its components use, or "") inside the transaction that marks it
# connected; a receiver may answer {skill: {"url", "token"}} of the cloud relays the cloud runs for its Skills.
cloud_relays_wanted = Signal()
