"""What every ROS 2 use-case node shares: start-up in the router's namespace, QoS, stamps, spinning."""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any, cast

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.utilities import remove_ros_args

from bridgeos_agent.usecases.__main__ import default_namespace
from bridgeos_agent.usecases.rosio import Metrics

__all__ = ["latched", "node_args", "reliable", "seq", "spin", "stamp_ns", "start", "subscribe_counted"]


def node_args(argv: list[str]) -> list[str]:
    """Return a node's own arguments: its command line without the ``--ros-args`` part."""
    return remove_ros_args(args=["node", *argv])[1:]


def start(name: str, argv: list[str]) -> Node:
    """Initialise rclpy with the command line's ROS args and make the node in its namespace.

    A ``__ns`` remap (what the Skill Router appends) wins; else ``ROS_NAMESPACE``; else the Skill's
    default ``/bridgeos/ROBOT/SKILL`` when the agent ran it without a router.
    """
    rclpy.init(args=["node", *argv])
    namespace = os.environ.get("ROS_NAMESPACE") or default_namespace(dict(os.environ)) or ""
    return rclpy.create_node(name, namespace=namespace)


def reliable(depth: int = 10) -> QoSProfile:
    """Return a reliable, volatile profile keeping the last ``depth`` messages (ROS 1's queue_size)."""
    return QoSProfile(history=HistoryPolicy.KEEP_LAST, depth=depth, reliability=ReliabilityPolicy.RELIABLE)


def latched(depth: int = 1) -> QoSProfile:
    """Return ROS 1's latch in ROS 2: reliable and transient-local, so late joiners get the last message."""
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=depth,
        reliability=ReliabilityPolicy.RELIABLE,
        durability=DurabilityPolicy.TRANSIENT_LOCAL,
    )


def stamp_ns(stamp: Any) -> int:
    """Return a builtin_interfaces/Time as nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def seq(info: Any) -> int:
    """Return a message's publication sequence number (ROS 2's headers have no seq: the middleware counts)."""
    return int(info["publication_sequence_number"])


def subscribe_counted(
    node: Node, msg_type: type, topic: str, callback: Callable[[Any, Any], None], qos: QoSProfile
) -> Any:
    """Subscribe with a callback that also gets the message's info (its publication sequence number)."""
    # rclpy passes the MessageInfo to a callback of two parameters; its annotation only knows one.
    return node.create_subscription(msg_type, topic, cast(Callable[[Any], None], callback), qos)


def spin(node: Node, metrics: Metrics | None = None) -> int:
    """Spin the node until SIGINT or SIGTERM, then post what metrics are pending and shut down."""
    try:
        rclpy.spin(node)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise
        # A callback that ran into the shutdown a signal began: nothing went wrong.
    finally:
        if metrics is not None:
            metrics.close()
        node.destroy_node()
        rclpy.try_shutdown()
    return 0
