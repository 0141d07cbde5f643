"""What a bridge needs of a robot's ROS graph, ROS 1 or ROS 2: topics, services, parameters and types.

A bridge protocol (rosbridge v2, Foxglove WebSocket; MCAP recording later) talks to one
``BridgeGraph`` and never to rclpy or TCPROS itself. Messages come off the graph as ``Sample``s:
their serialized bytes, decoded to plain data (dicts, lists, ``bytes`` for byte arrays) only when
a client needs them, and then once for every client.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import Any, Protocol

__all__ = [
    "BridgeError",
    "BridgeGraph",
    "GraphActionGoal",
    "GraphPublisher",
    "GraphSubscription",
    "Sample",
    "ServiceHandler",
]

ServiceHandler = Callable[[dict[str, Any]], Awaitable[dict[str, Any]]]


class BridgeError(Exception):
    """A request the graph cannot carry out; the text is what the client is told."""


class GoalOutcome(BridgeError):
    """A well-formed action goal that did not run: no server answered, it was rejected, or the graph has none."""


class Sample:
    """One message off the graph: its serialized bytes, decoded on first use and cached."""

    __slots__ = ("_decode", "_msg", "frames", "raw", "stamp")

    def __init__(
        self, raw: bytes | memoryview, decode: Callable[[Any], dict[str, Any]], stamp: tuple[int, int]
    ) -> None:
        self.raw = raw
        self.stamp = stamp  # (seconds, nanoseconds) of the graph's clock when it arrived
        self._decode = decode
        self._msg: dict[str, Any] | None = None
        # Encoded frames by encoding, so a message sent to many clients is encoded once.
        self.frames: dict[Any, Any] = {}

    def msg(self) -> dict[str, Any]:
        """Return the message as plain data."""
        if self._msg is None:
            self._msg = self._decode(self.raw)
        return self._msg


class GraphSubscription(Protocol):
    """A subscription of the bridge in the graph."""

    type: str

    def close(self) -> None:
        """Leave the topic."""


class GraphPublisher(Protocol):
    """A publisher of the bridge in the graph."""

    type: str

    def publish(self, msg: dict[str, Any]) -> None:
        """Publish one message given as plain data; raise BridgeError naming a bad field."""

    def publish_raw(self, raw: bytes) -> None:
        """Publish one message given serialized in the graph's own encoding; raise BridgeError if it does not read."""

    def close(self) -> None:
        """Stop publishing."""


class GraphActionGoal(Protocol):
    """A goal the bridge sent to an action server of the graph, which accepted it."""

    async def result(self) -> tuple[int, dict[str, Any]]:
        """Wait for the goal to end; return its status (action_msgs/GoalStatus) and its result as plain data."""

    async def cancel(self, timeout: float) -> None:
        """Ask the server to cancel the goal; raise BridgeError with its reason when it will not."""


class BridgeGraph(Protocol):
    """A robot's ROS graph as the bridges see it."""

    ros_version: int  # 1 or 2
    message_encoding: str  # how its messages travel serialized: 'ros1' or 'cdr' (Foxglove's and MCAP's names)
    schema_encoding: str  # how its definitions are written: 'ros1msg' or 'ros2msg'

    def normalize_type(self, type_: str) -> str:
        """Return the graph's own spelling of a type ('pkg/Type' or 'pkg/msg/Type'), or raise BridgeError."""

    async def topics(self) -> dict[str, str]:
        """Return every topic of the graph with its type."""

    async def published_topics(self) -> dict[str, str]:
        """Return the topics someone publishes now, with their types."""

    async def services(self) -> dict[str, str]:
        """Return every service of the graph with its type ('' when it cannot be told)."""

    async def nodes(self) -> list[str]:
        """Return the full names of the graph's nodes."""

    async def subscribe(self, topic: str, type_: str | None, deliver: Callable[[Sample], None]) -> GraphSubscription:
        """Subscribe to a topic; ``deliver`` runs on the event loop for each message."""

    async def advertise(self, topic: str, type_: str) -> GraphPublisher:
        """Publish on a topic."""

    async def call_service(self, name: str, type_: str | None, args: dict[str, Any], timeout: float) -> dict[str, Any]:
        """Call a service of the graph and return its response as plain data."""

    async def call_service_raw(self, name: str, type_: str | None, request: bytes, timeout: float) -> bytes:
        """Call a service with a serialized request and return its serialized response."""

    def schema(self, type_: str) -> str:
        """Return a message type's full definition: its own, then each type inside it after a 'MSG:' line."""

    def service_schemas(self, type_: str) -> tuple[str, str]:
        """Return the full definitions of a service type's request and response."""

    async def advertise_service(self, name: str, type_: str, handler: ServiceHandler) -> GraphSubscription:
        """Serve a service in the graph, each call answered by ``handler``."""

    async def get_param(self, name: str) -> Any:
        """Return a parameter's value; raise KeyError when it is not set."""

    async def get_params(self, names: list[str] | None) -> dict[str, Any]:
        """Return the values of the parameters named (all when None) that are set; raise BridgeError for a bad name."""

    async def set_param(self, name: str, value: Any) -> None:
        """Set a parameter."""

    async def delete_param(self, name: str) -> None:
        """Delete a parameter; raise KeyError when it is not set."""

    async def param_names(self) -> list[str]:
        """Return the names of every parameter."""

    async def simulated_clock(self) -> bool:
        """Return whether the graph runs on simulated time, told on /clock (rosgraph_msgs/Clock)."""

    async def action_servers(self) -> dict[str, str]:
        """Return the actions a server serves now, with their types ('' when it cannot be told)."""

    async def send_action_goal(
        self,
        name: str,
        type_: str | None,
        goal: dict[str, Any],
        feedback: Callable[[dict[str, Any]], None] | None,
        timeout: float,
    ) -> GraphActionGoal:
        """Send a ROS 2 action goal (its feedback to ``feedback`` on the event loop); return once it is accepted.

        Raise BridgeError with the reason when it is not: no server, a goal that does not fit the
        type, a rejection, or a graph without ROS 2 actions.
        """

    def now(self) -> tuple[int, int]:
        """Return the graph's time as (seconds, nanoseconds)."""

    def time_message(self, seconds: int, nanoseconds: int) -> dict[str, int]:
        """Return a time as this ROS spells it in a message."""

    def message_details(self, type_: str) -> list[dict[str, Any]]:
        """Return rosapi's TypeDefs of a message type and every type inside it."""

    async def close(self) -> None:
        """Leave the graph."""
