"""A robot's ROS 2 graph for the bridges: rclpy nodes in the process's shared Context of that graph.

Messages are taken raw by the router's ``RelayLoop`` (one thread, no executor per message) and
decoded only when a client needs them. Parameters belong to nodes in ROS 2: they are named
``/node_name:parameter`` (as rosbridge_suite's ROS 2 rosapi names them) and read and written
through that node's own parameter services.
"""

from __future__ import annotations

import array
import asyncio
import base64
import contextlib
import logging
import threading
import time
from collections.abc import Callable
from typing import Any

from bridgeos_agent.bridges.graph import BridgeError, Sample, ServiceHandler
from bridgeos_agent.bridges.ros2actions import Ros2ActionGoal, Ros2Actions
from bridgeos_agent.bridges.ros2defs import message_definition, service_definitions
from bridgeos_agent.bridges.ros2params import Ros2Params
from bridgeos_agent.ros2graph import Ros2Graph, Ros2TypeError, interface_class

__all__ = ["Ros2BridgeGraph", "fill_message", "message_to_plain"]

logger = logging.getLogger(__name__)


def ros2_name(type_: str, kind: str = "msg") -> str:
    """Return 'pkg/kind/Type' for 'pkg/Type' or 'pkg/kind/Type'; raise BridgeError otherwise."""
    parts = type_.strip("/").split("/")
    if len(parts) == 2:
        parts = [parts[0], kind, parts[1]]
    if len(parts) != 3 or parts[1] != kind or not all(p and p.replace("_", "").isalnum() for p in parts):
        raise BridgeError(f"{type_!r} is not a ROS 2 {kind} type ('package/{kind}/Type')")
    return "/".join(parts)


def _load(type_: str, kind: str = "msg") -> Any:
    try:
        return interface_class(ros2_name(type_, kind), kind)  # type: ignore[arg-type]
    except Ros2TypeError as exc:
        raise BridgeError(f"unknown type {type_}: {exc}") from None


def message_to_plain(message: Any) -> dict[str, Any]:
    """Return an rclpy message as plain data: byte arrays as bytes, other arrays as lists."""
    return {field: _plain(getattr(message, field)) for field in message.get_fields_and_field_types()}


def _plain(value: Any) -> Any:
    if hasattr(value, "get_fields_and_field_types"):
        return message_to_plain(value)
    if isinstance(value, array.array):
        return value.tobytes() if value.typecode == "B" else value.tolist()
    if isinstance(value, list | tuple):
        if value and isinstance(value[0], bytes):  # byte[]: a list of one-byte bytes
            return b"".join(value)
        return [_plain(item) for item in value]
    tolist = getattr(value, "tolist", None)  # numpy arrays (fixed-size) and numpy scalars
    if tolist is not None:
        if str(getattr(value, "dtype", "")) == "uint8" and hasattr(value, "tobytes") and value.shape:
            return value.tobytes()
        return tolist()
    return value


def fill_message(message: Any, data: Any, path: str) -> None:
    """Set an rclpy message's fields from plain data; raise BridgeError naming the first bad field."""
    from rosidl_parser.definition import AbstractGenericString, AbstractNestedType, BasicType, NamespacedType

    if not isinstance(data, dict):
        raise BridgeError(f"{path}: expected an object, not {type(data).__name__}")
    fields = message.get_fields_and_field_types()
    if type(message).__module__.startswith("builtin_interfaces") and ("secs" in data or "nsecs" in data):
        # ROS 1 clients (and roslibpy) spell a time secs/nsecs.
        data = {"sec": data.get("secs", 0), "nanosec": data.get("nsecs", 0)}
    slots = dict(zip(fields, message.SLOT_TYPES, strict=True))
    for key, value in data.items():
        where = f"{path}.{key}"
        slot = slots.get(key)
        if slot is None:
            raise BridgeError(f"{path} has no field {key!r} (fields: {', '.join(fields)})")
        try:
            if isinstance(slot, NamespacedType):
                fill_message(getattr(message, key), value, where)
                continue
            if isinstance(slot, AbstractNestedType):
                inner = slot.value_type
                if isinstance(inner, NamespacedType):
                    cls = interface_class("/".join([*inner.namespaces, inner.name]), inner.namespaces[-1])
                    if not isinstance(value, list):
                        raise BridgeError(f"{where}: expected a list")
                    items = []
                    for index, item in enumerate(value):
                        element = cls()
                        fill_message(element, item, f"{where}[{index}]")
                        items.append(element)
                    value = items
                elif isinstance(inner, BasicType) and inner.typename in ("uint8", "char", "octet"):
                    if isinstance(value, str):
                        value = base64.b64decode(value, validate=True)
                    if inner.typename == "octet" and isinstance(value, bytes | bytearray):
                        value = [bytes([b]) for b in value]
                    elif isinstance(value, bytes | bytearray):
                        value = list(value)
                elif isinstance(inner, BasicType | AbstractGenericString):
                    if not isinstance(value, list):
                        raise BridgeError(f"{where}: expected a list, not {type(value).__name__}")
                    value = [_basic(inner, item, f"{where}[{i}]") for i, item in enumerate(value)]
            elif isinstance(slot, BasicType | AbstractGenericString):
                value = _basic(slot, value, where)
            setattr(message, key, value)
        except BridgeError:
            raise
        except (AssertionError, TypeError, ValueError, OverflowError) as exc:
            raise BridgeError(f"{where}: {exc or 'bad value'}"[:300]) from None


_INT_BITS = {"int8": 8, "int16": 16, "int32": 32, "int64": 64}


def _basic(slot: Any, value: Any, where: str) -> Any:
    """Check (and where lossless, convert) one value for a basic or string field.

    rclpy checks field types only when ROS_PYTHON_CHECK_FIELDS is set; unchecked, a wrong type
    fails later, in serialization, without naming the field.
    """
    from rosidl_parser.definition import AbstractGenericString

    if isinstance(slot, AbstractGenericString):
        if not isinstance(value, str):
            raise BridgeError(f"{where}: expected a string, not {type(value).__name__}")
        return value
    kind = slot.typename
    if kind == "boolean":
        if not isinstance(value, bool):
            raise BridgeError(f"{where}: expected true or false, not {value!r}"[:200])
        return value
    if kind in ("float", "double", "long double"):
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise BridgeError(f"{where}: expected a number, not {value!r}"[:200])
        return float(value)
    if kind == "octet":
        if isinstance(value, int) and not isinstance(value, bool) and 0 <= value < 256:
            return bytes([value])
        if isinstance(value, bytes) and len(value) == 1:
            return value
        raise BridgeError(f"{where}: expected a byte, not {value!r}"[:200])
    if isinstance(value, float) and value.is_integer():
        value = int(value)
    if isinstance(value, bool) or not isinstance(value, int):
        raise BridgeError(f"{where}: expected an integer, not {value!r}"[:200])
    if kind.startswith("uint") or kind == "char":
        bits = int(kind[4:]) if kind.startswith("uint") else 8
        low, high = 0, 2**bits - 1
    else:
        bits = _INT_BITS.get(kind, 64)
        low, high = -(2 ** (bits - 1)), 2 ** (bits - 1) - 1
    if not low <= value <= high:
        raise BridgeError(f"{where}: {value} is out of range for {kind}")
    return value


class _Handle:
    def __init__(self, type_: str, close: Callable[[], Any]) -> None:
        self.type = type_
        self._close = close

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._close()


class _Publisher:
    def __init__(self, type_: str, cls: Any, publisher: Any, destroy: Callable[[Any], Any]) -> None:
        self.type = type_
        self.cls = cls
        self.publisher = publisher
        self._destroy = destroy

    def publish(self, msg: dict[str, Any]) -> None:
        message = self.cls()
        fill_message(message, msg, self.type)
        self.publisher.publish(message)

    def publish_raw(self, raw: bytes) -> None:
        _deserialize(raw, self.cls, self.type)  # a message that does not read never reaches the robot's nodes
        self.publisher.publish(bytes(raw))

    def close(self) -> None:
        with contextlib.suppress(Exception):
            self._destroy(self.publisher)


class Ros2BridgeGraph:
    """The robot's ROS 2 graph, joined by one node of the bridge and a raw relay for its subscriptions."""

    ros_version = 2
    message_encoding = "cdr"
    schema_encoding = "ros2msg"

    def __init__(self, graph: Ros2Graph, loop: asyncio.AbstractEventLoop, *, name: str = "bridgeos_rosbridge") -> None:
        import rclpy
        from rclpy.callback_groups import ReentrantCallbackGroup
        from rclpy.executors import MultiThreadedExecutor

        from bridgeos_agent.router.ros2graphs import RelayLoop, joined

        self.loop = loop
        with joined(graph) as context:
            self.context = context
            self.node = rclpy.create_node(name, context=context)
            self.relay_node = rclpy.create_node(
                name + "_relay", context=context, enable_rosout=False, start_parameter_services=False
            )
        self.group = ReentrantCallbackGroup()
        self._executor = MultiThreadedExecutor(num_threads=4, context=context)
        self._executor.add_node(self.node)
        self._thread = threading.Thread(target=self._spin, name="ros2-rosbridge", daemon=True)
        self._thread.start()
        self.relay = RelayLoop(context, self.relay_node, "rosbridge")
        self._clients: dict[tuple[str, str], Any] = {}
        self.params = Ros2Params(self._request, self.nodes)
        self.actions = Ros2Actions(self.node, self.group, loop)

    def _spin(self) -> None:
        from rclpy.executors import ExternalShutdownException

        with contextlib.suppress(ExternalShutdownException):
            self._executor.spin()

    async def close(self) -> None:
        """Leave the graph (the process's Context of it stays for its other users)."""
        self.relay.close()
        self.actions.close()
        self._executor.shutdown(timeout_sec=2)
        with contextlib.suppress(Exception):
            self.node.destroy_node()
            self.relay_node.destroy_node()
        self._thread.join(2)

    def normalize_type(self, type_: str) -> str:
        """Return 'pkg/msg/Type'."""
        return ros2_name(type_)

    # ------------------------------------------------------------------ graph

    async def topics(self) -> dict[str, str]:
        """Return every topic with its (first) type."""
        return {name: types[0] for name, types in self.node.get_topic_names_and_types() if types}

    async def published_topics(self) -> dict[str, str]:
        """Return the topics with a publisher now, with their (first) type."""
        return {
            name: types[0]
            for name, types in self.node.get_topic_names_and_types()
            if types and self.node.count_publishers(name)
        }

    async def services(self) -> dict[str, str]:
        """Return every service with its type."""
        return {name: types[0] for name, types in self.node.get_service_names_and_types() if types}

    async def nodes(self) -> list[str]:
        """Return the full names of the graph's nodes."""
        # A node is listed once per participant that saw it: count it once.
        return sorted(
            {f"{namespace.rstrip('/')}/{name}" for name, namespace in self.node.get_node_names_and_namespaces()}
        )

    # ------------------------------------------------------------------ topics

    def _qos(self, topic: str) -> Any:
        """Match the publishers: best effort if any is, transient local only if all are (latched topics)."""
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

        infos = self.node.get_publishers_info_by_topic(topic)
        best_effort = any(i.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for i in infos)
        latched = bool(infos) and all(i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for i in infos)
        return QoSProfile(
            depth=100,
            reliability=ReliabilityPolicy.BEST_EFFORT if best_effort else ReliabilityPolicy.RELIABLE,
            durability=DurabilityPolicy.TRANSIENT_LOCAL if latched else DurabilityPolicy.VOLATILE,
        )

    async def subscribe(self, topic: str, type_: str | None, deliver: Callable[[Sample], None]) -> _Handle:
        """Subscribe raw; each message reaches ``deliver`` on the event loop, decoded only when read."""
        from rclpy.serialization import deserialize_message

        known = dict(self.node.get_topic_names_and_types()).get(topic) or []
        wanted = ros2_name(type_) if type_ else (known[0] if known else None)
        if wanted is None:
            raise BridgeError(f"{topic} does not exist; give its type to subscribe before anyone publishes it")
        if known and wanted not in known:
            raise BridgeError(f"{topic} is of type {known[0]}, not {wanted}")
        cls = _load(wanted)
        loop = self.loop

        def decode(raw: bytes) -> dict[str, Any]:
            return message_to_plain(deserialize_message(raw, cls))

        def handler(data: bytes, info: dict[str, Any]) -> None:
            stamp = time.time_ns()
            sample = Sample(data, decode, (stamp // 1_000_000_000, stamp % 1_000_000_000))
            loop.call_soon_threadsafe(deliver, sample)

        subscription = self.relay.subscribe(cls, topic, self._qos(topic), handler)
        return _Handle(wanted, lambda: self.relay.unsubscribe(subscription))

    async def advertise(self, topic: str, type_: str) -> _Publisher:
        """Publish a topic, reliable and volatile (rclpy's default)."""
        wanted = ros2_name(type_)
        cls = _load(wanted)
        try:
            publisher = self.node.create_publisher(cls, topic, 10)
        except Exception as exc:  # rclpy rejects bad names with its own exceptions
            raise BridgeError(f"cannot publish {topic}: {exc}") from None
        return _Publisher(wanted, cls, publisher, self.node.destroy_publisher)

    # ------------------------------------------------------------------ services

    async def _request(self, name: str, srv_type: str, cls: Any, request: Any, timeout: float) -> Any:
        client = self._clients.get((name, srv_type))
        if client is None:
            client = self._clients[(name, srv_type)] = self.node.create_client(cls, name, callback_group=self.group)
        if not client.service_is_ready():
            ready = await self.loop.run_in_executor(None, client.wait_for_service, min(timeout, 2.0))
            if not ready:
                raise BridgeError(f"no server answers {name}")
        future = client.call_async(request)
        answer: asyncio.Future[Any] = self.loop.create_future()

        def done(result: Any) -> None:
            if not answer.done():
                if result.exception() is not None:
                    answer.set_exception(BridgeError(f"{name}: {result.exception()}"))
                else:
                    answer.set_result(result.result())

        future.add_done_callback(lambda result: self.loop.call_soon_threadsafe(done, result))
        try:
            return await asyncio.wait_for(answer, timeout)
        except TimeoutError:
            client.remove_pending_request(future)
            raise BridgeError(f"{name} did not answer within {timeout:g} s") from None

    async def call_service(self, name: str, type_: str | None, args: dict[str, Any], timeout: float) -> dict[str, Any]:
        """Call a service of the graph."""
        srv_type = self._service_type(name, type_)
        cls = _load(srv_type, "srv")
        request = cls.Request()
        fill_message(request, args, srv_type + ".Request")
        return message_to_plain(await self._request(name, srv_type, cls, request, timeout))

    async def call_service_raw(self, name: str, type_: str | None, request: bytes, timeout: float) -> bytes:
        """Call a service with a CDR-serialized request; return the CDR-serialized response."""
        from rclpy.serialization import serialize_message

        srv_type = self._service_type(name, type_)
        cls = _load(srv_type, "srv")
        message = _deserialize(request, cls.Request, srv_type + ".Request")
        return bytes(serialize_message(await self._request(name, srv_type, cls, message, timeout)))

    def _service_type(self, name: str, type_: str | None) -> str:
        known = dict(self.node.get_service_names_and_types()).get(name) or []
        srv_type = ros2_name(type_, "srv") if type_ else (known[0] if known else None)
        if srv_type is None:
            raise BridgeError(f"no service {name} in the ROS graph")
        if known and srv_type not in known:
            raise BridgeError(f"{name} is of type {known[0]}, not {srv_type}")
        return srv_type

    async def advertise_service(self, name: str, type_: str, handler: ServiceHandler) -> _Handle:
        """Serve a service whose calls are answered by ``handler`` (a failed call answers the default response)."""
        srv_type = ros2_name(type_, "srv")
        cls = _load(srv_type, "srv")
        loop = self.loop

        def serve(request: Any, response: Any) -> Any:
            try:
                values = asyncio.run_coroutine_threadsafe(_call(handler, message_to_plain(request)), loop).result()
                fill_message(response, values, srv_type + ".Response")
            except Exception as exc:  # ROS 2 services have no error answer: the caller gets the defaults
                logger.warning("rosbridge: %s failed: %s", name, exc)
            return response

        try:
            service = self.node.create_service(cls, name, serve, callback_group=self.group)
        except Exception as exc:
            raise BridgeError(f"cannot serve {name}: {exc}") from None
        return _Handle(srv_type, lambda: self.node.destroy_service(service))

    # ------------------------------------------------------------------ parameters and actions

    async def get_param(self, name: str) -> Any:
        """Return a node's parameter ('/node:parameter')."""
        return await self.params.get(name)

    async def get_params(self, names: list[str] | None) -> dict[str, Any]:
        """Return the values of the parameters named (every one when None) that are set."""
        return await self.params.values(names)

    async def set_param(self, name: str, value: Any) -> None:
        """Set a node's parameter (the node may refuse: its reason is passed on)."""
        await self.params.set(name, value)

    async def delete_param(self, name: str) -> None:
        """Undeclare a node's parameter (nodes that allow it only)."""
        await self.params.delete(name)

    async def param_names(self) -> list[str]:
        """Return '/node:parameter' for every parameter of every node that answers."""
        return await self.params.names()

    async def action_servers(self) -> dict[str, str]:
        """Return the actions a server serves now, with their types."""
        return self.actions.servers()

    async def send_action_goal(
        self,
        name: str,
        type_: str | None,
        goal: dict[str, Any],
        feedback: Callable[[dict[str, Any]], None] | None,
        timeout: float,
    ) -> Ros2ActionGoal:
        """Send a goal to an action server of the graph; return once the server accepted it."""
        return await self.actions.send_goal(name, type_, goal, feedback, timeout)

    # ------------------------------------------------------------------ time and types

    def schema(self, type_: str) -> str:
        """Return a message type's full ros2msg definition, from its package's installed .msg files."""
        return message_definition(ros2_name(type_))

    def service_schemas(self, type_: str) -> tuple[str, str]:
        """Return the full ros2msg definitions of a service's request and response."""
        return service_definitions(ros2_name(type_, "srv"))

    async def simulated_clock(self) -> bool:
        """Return whether someone publishes /clock (rosgraph_msgs/Clock): the graph runs on simulated time."""
        types = dict(self.node.get_topic_names_and_types()).get("/clock") or []
        return "rosgraph_msgs/msg/Clock" in types and bool(self.node.count_publishers("/clock"))

    def now(self) -> tuple[int, int]:
        """Return the bridge node's clock."""
        seconds, nanoseconds = self.node.get_clock().now().seconds_nanoseconds()
        return int(seconds), int(nanoseconds)

    def time_message(self, seconds: int, nanoseconds: int) -> dict[str, int]:
        """Return a time spelled both ways: ROS 2's sec/nanosec, and the secs/nsecs roslibpy reads."""
        return {"sec": seconds, "nanosec": nanoseconds, "secs": seconds, "nsecs": nanoseconds}

    def message_details(self, type_: str) -> list[dict[str, Any]]:
        """Return rosapi's TypeDefs of a message type and the types inside it."""
        out: list[dict[str, Any]] = []
        queue, seen = [ros2_name(type_)], set()
        while queue:
            name = queue.pop(0)
            if name in seen:
                continue
            seen.add(name)
            cls = _load(name)
            constants = next(
                (v for k, v in vars(type(cls)).items() if k.endswith("__constants") and isinstance(v, dict)), {}
            )
            typedef: dict[str, Any] = {
                "type": name,
                "fieldnames": [],
                "fieldtypes": [],
                "fieldarraylen": [],
                "examples": [],
                "constnames": list(constants),
                "constvalues": [str(v) for v in constants.values()],
            }
            for field, spelled in cls.get_fields_and_field_types().items():
                length = -1
                base = spelled
                if spelled.startswith("sequence<"):
                    base, length = spelled[9:-1].split(",")[0].strip(), 0
                elif spelled.endswith("]"):
                    base, _, count = spelled[:-1].partition("[")
                    length = int(count) if count.isdigit() else 0
                if "/" in base:
                    package, short = base.split("/")
                    base = f"{package}/msg/{short}"
                    queue.append(base)
                typedef["fieldnames"].append(field)
                typedef["fieldtypes"].append(base)
                typedef["fieldarraylen"].append(length)
                typedef["examples"].append("[]" if length >= 0 else "{}" if "/" in base else "")
            out.append(typedef)
        return out


def _deserialize(raw: bytes, cls: Any, type_: str) -> Any:
    from rclpy.serialization import deserialize_message

    try:
        return deserialize_message(bytes(raw), cls)
    except Exception as exc:  # rclpy raises its own RMWError for bytes that are not the type's CDR
        raise BridgeError(f"{len(raw)} bytes are not a CDR-serialized {type_}: {exc}"[:300]) from None


async def _call(handler: ServiceHandler, request: dict[str, Any]) -> dict[str, Any]:
    return await handler(request)
