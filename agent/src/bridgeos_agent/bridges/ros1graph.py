"""A robot's ROS 1 graph for the bridges: the agent's own asyncio ROS node, messages read with rosbags."""

from __future__ import annotations

import asyncio
import contextlib
import time
import xmlrpc.client
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

from bridgeos_agent.bridges.graph import BridgeError, GoalOutcome, Sample, ServiceHandler
from bridgeos_agent.bridges.ros1types import Ros1Types, ros1_name
from bridgeos_agent.rosnode import Inbound, MasterError, RosNode, Subscription, iter_frames, read_header
from bridgeos_agent.tcpros import HeaderError, encode_header, frame

__all__ = ["Ros1Graph"]

PROBE_TIMEOUT = 2.0


class _Subscription:
    def __init__(self, graph: Ros1Graph, topic: str, type_: str, deliver: Callable[[Sample], None]) -> None:
        self.graph = graph
        self.topic = topic
        self.type = type_
        self.deliver = deliver

    def close(self) -> None:
        self.graph._leave(self)


class _Publisher:
    def __init__(self, graph: Ros1Graph, topic: str, type_: str) -> None:
        self.graph = graph
        self.topic = topic
        self.type = type_
        self._name = graph.types.ensure_message(type_)
        self.publication = graph.node.advertise(topic, type_)
        self.publication.definition, self.publication.md5sum = graph.types.definition(type_)

    def publish(self, msg: dict[str, Any]) -> None:
        raw = self.graph.types.encode(self._name, msg)
        self.publication.send(frame(raw), 1)
        self.graph._loop_back(self.topic, self.type, raw)

    def publish_raw(self, raw: bytes) -> None:
        self.graph.types.decode(self._name, raw)  # a message that does not read never reaches the robot's nodes
        self.publication.send(frame(raw), 1)
        self.graph._loop_back(self.topic, self.type, raw)

    def close(self) -> None:
        self.graph.node.unadvertise(self.topic)


class _Service:
    def __init__(self, graph: Ros1Graph, name: str) -> None:
        self.graph = graph
        self.name = name
        self.type = ""

    def close(self) -> None:
        self.graph.node.unadvertise_service(self.name)


class Ros1Graph:
    """The graph of one ROS master, joined as one node."""

    ros_version = 1
    message_encoding = "ros1"
    schema_encoding = "ros1msg"

    def __init__(self, master_uri: str, *, name: str = "/bridgeos_rosbridge", host: str = "127.0.0.1") -> None:
        self.types = Ros1Types()
        self.node = RosNode(name, master_uri, host=host, on_publisher_header=self._on_header)
        self._service_types: dict[tuple[str, str], str] = {}
        # The node subscribes a topic once; every bridge subscription of it (rosbridge, Foxglove, the
        # recorder) hears each message from that one connection.
        self._listeners: dict[str, list[_Subscription]] = {}
        self._decoders: dict[str, Callable[[bytes], dict[str, Any]]] = {}

    async def start(self) -> None:
        """Register with the master (raises MasterError when it does not answer)."""
        await self.node.start()

    async def close(self) -> None:
        """Unregister and close every connection."""
        await self.node.close()

    def normalize_type(self, type_: str) -> str:
        """Return 'pkg/Type'."""
        return ros1_name(type_)

    def _on_header(self, subscription: Subscription, inbound: Inbound) -> None:
        header = inbound.header or {}
        with contextlib.suppress(BridgeError):
            self.types.learn(header.get("type", subscription.type), header.get("message_definition", ""))

    async def _master(self, method: str, *params: Any) -> Any:
        try:
            return await self.node.master_call(method, *params)
        except MasterError as exc:
            raise BridgeError(str(exc)) from None

    # ------------------------------------------------------------------ graph

    async def topics(self) -> dict[str, str]:
        """Return the topics the master knows (published or subscribed) with their types."""
        return {name: type_ for name, type_ in await self._master("getTopicTypes")}

    async def published_topics(self) -> dict[str, str]:
        """Return the topics with a publisher now (the master keeps every topic it ever saw in getTopicTypes)."""
        return {name: type_ for name, type_ in await self._master("getPublishedTopics", "")}

    async def _state(self) -> tuple[list[Any], list[Any], list[Any]]:
        publishers, subscribers, services = await self._master("getSystemState")
        return publishers, subscribers, services

    async def nodes(self) -> list[str]:
        """Return every node that publishes, subscribes or serves something."""
        names: set[str] = set()
        for group in await self._state():
            for _, members in group:
                names.update(members)
        return sorted(names)

    async def services(self) -> dict[str, str]:
        """Return the services with their types, asked of each server once (as rosservice does)."""
        _, _, services = await self._state()
        names = [name for name, _ in services]
        types = await asyncio.gather(*(self._service_type(name) for name in names))
        return dict(zip(names, types, strict=True))

    async def _service_type(self, name: str) -> str:
        try:
            uri = await self.node.master_call("lookupService", name)
        except MasterError:
            return ""
        known = self._service_types.get((name, uri))
        if known is not None:
            return known
        parts = urlsplit(uri)
        try:
            async with asyncio.timeout(PROBE_TIMEOUT):
                reader, writer = await asyncio.open_connection(parts.hostname, parts.port)
                try:
                    writer.write(
                        encode_header({"probe": "1", "md5sum": "*", "callerid": self.node.name, "service": name})
                    )
                    header = await read_header(reader)
                finally:
                    writer.close()
        except (OSError, TimeoutError, HeaderError, asyncio.IncompleteReadError, ValueError):
            return ""
        type_ = header.get("type", "")
        self._service_types[(name, uri)] = type_
        return type_

    # ------------------------------------------------------------------ topics

    async def subscribe(self, topic: str, type_: str | None, deliver: Callable[[Sample], None]) -> _Subscription:
        """Subscribe with md5sum '*' and decode each message with its publisher's own definition."""
        known = (await self.topics()).get(topic)
        wanted = ros1_name(type_) if type_ else known
        if wanted is None:
            raise BridgeError(f"{topic} does not exist; give its type to subscribe before anyone publishes it")
        if known is not None and known != wanted:
            raise BridgeError(f"{topic} is of type {known}, not {wanted}")
        listeners = self._listeners.get(topic)
        if listeners:
            if listeners[0].type != wanted:
                raise BridgeError(f"{topic} is subscribed as {listeners[0].type}, not {wanted}")
            subscription = _Subscription(self, topic, wanted, deliver)
            listeners.append(subscription)
            return subscription
        with contextlib.suppress(BridgeError):  # a type only the publisher can define is learned from its header
            self.types.ensure_message(wanted)
        name = "{}/msg/{}".format(*wanted.split("/"))
        types = self.types

        def decode(raw: bytes) -> dict[str, Any]:
            if name not in types.store.fielddefs:
                raise BridgeError(f"no definition of {wanted} is known yet")
            return types.decode(name, raw)

        listeners = self._listeners[topic] = [_Subscription(self, topic, wanted, deliver)]
        self._decoders[topic] = decode

        def received(subscription: Subscription, blob: bytes, count: int, inbound: Inbound) -> None:
            stamp = time.time_ns()
            stamp_pair = (stamp // 1_000_000_000, stamp % 1_000_000_000)
            view = memoryview(blob)
            offset = 0
            for one in iter_frames(blob) if count != 1 else (blob,):
                size = len(one)
                sample = Sample(view[offset + 4 : offset + size], decode, stamp_pair)
                for listener in listeners:
                    listener.deliver(sample)
                offset += size

        self.node.subscribe(topic, wanted, received)
        try:
            await self._settle()
        except BaseException:
            self._leave(listeners[0])
            raise
        return listeners[0]

    def _leave(self, subscription: _Subscription) -> None:
        """Forget one bridge subscription; the node unsubscribes with the topic's last."""
        listeners = self._listeners.get(subscription.topic)
        if listeners is None or subscription not in listeners:
            return
        listeners.remove(subscription)
        if not listeners:
            del self._listeners[subscription.topic]
            del self._decoders[subscription.topic]
            self.node.unsubscribe(subscription.topic)

    def _loop_back(self, topic: str, type_: str, raw: bytes) -> None:
        """Hand a message the node publishes to its own subscriptions of the topic.

        A node never connects to itself (the router relies on that to publish what it subscribes
        without echoes), so a bridge client's message would reach every node but this one; rospy
        and rosbridge_server deliver a node's publications to its own subscribers, and so do we.
        """
        listeners = self._listeners.get(topic)
        if not listeners or listeners[0].type != type_:
            return
        stamp = time.time_ns()
        sample = Sample(raw, self._decoders[topic], (stamp // 1_000_000_000, stamp % 1_000_000_000))
        for listener in list(listeners):
            listener.deliver(sample)

    async def advertise(self, topic: str, type_: str) -> _Publisher:
        """Publish a topic with the md5sum and definition of its type."""
        publisher = _Publisher(self, topic, ros1_name(type_))
        await self._settle()
        return publisher

    async def _settle(self) -> None:
        errors = await self.node.settle()
        if errors:
            raise BridgeError("; ".join(str(e) for e in errors))

    # ------------------------------------------------------------------ services

    async def call_service(self, name: str, type_: str | None, args: dict[str, Any], timeout: float) -> dict[str, Any]:
        """Call a service once over its own TCPROS connection."""

        def request(served: str) -> bytes:
            return self.types.encode(self.types.ensure_service(served)[0], args)

        served, body = await self._exchange(name, type_, request, timeout)
        return self.types.decode(self.types.ensure_service(served)[1], body)

    async def call_service_raw(self, name: str, type_: str | None, request: bytes, timeout: float) -> bytes:
        """Call a service with a request serialized as ROS 1 does; return the serialized response."""
        return (await self._exchange(name, type_, lambda served: request, timeout))[1]

    async def _exchange(
        self, name: str, type_: str | None, request: Callable[[str], bytes], timeout: float
    ) -> tuple[str, bytes]:
        """Send one request (made once the server named its type) and return that type and the response."""
        where = await self.node.lookup_service(name)
        if where is None:
            raise BridgeError(f"no service {name} in the ROS graph")
        try:
            reader, writer = await asyncio.wait_for(asyncio.open_connection(*where), timeout)
        except (OSError, TimeoutError) as exc:
            raise BridgeError(f"cannot reach {name}: {exc}") from None
        try:
            writer.write(encode_header({"callerid": self.node.name, "service": name, "md5sum": "*", "persistent": "0"}))
            header = await asyncio.wait_for(read_header(reader), timeout)
            if "error" in header:
                raise BridgeError(f"{name} refused the call: {header['error']}")
            served = header.get("type") or (ros1_name(type_) if type_ else "")
            if type_ and served and ros1_name(type_) != served:
                raise BridgeError(f"{name} is of type {served}, not {type_}")
            writer.write(frame(request(served)))
            ok = await reader.readexactly(1)
            size = int.from_bytes(await reader.readexactly(4), "little")
            body = await reader.readexactly(size)
        except (OSError, HeaderError, asyncio.IncompleteReadError) as exc:
            raise BridgeError(f"{name}: the connection failed: {exc or type(exc).__name__}") from None
        finally:
            writer.close()
        if ok != b"\x01":
            raise BridgeError(f"{name} failed: {body.decode('utf-8', 'replace')}")
        return served, body

    async def advertise_service(self, name: str, type_: str, handler: ServiceHandler) -> _Service:
        """Serve a service whose calls are answered by ``handler``."""
        served = ros1_name(type_)
        request, response = self.types.ensure_service(served)
        types = self.types

        async def serve(header: dict[str, str], reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            writer.write(
                encode_header(
                    {
                        "callerid": self.node.name,
                        "md5sum": header.get("md5sum", "*"),
                        "type": served,
                        "request_type": served + "Request",
                        "response_type": served + "Response",
                    }
                )
            )
            if header.get("probe") == "1":
                return
            while True:
                try:
                    size = int.from_bytes(await reader.readexactly(4), "little")
                    body = await reader.readexactly(size)
                except (asyncio.IncompleteReadError, ConnectionError):
                    return
                try:
                    answer = types.encode(response, await handler(types.decode(request, body)))
                except BridgeError as exc:
                    writer.write(b"\x00" + frame(str(exc).encode()))
                else:
                    writer.write(b"\x01" + frame(answer))
                await writer.drain()

        self.node.advertise_service(name, serve)
        await self._settle()
        service = _Service(self, name)
        service.type = served
        return service

    # ------------------------------------------------------------------ parameters and time

    async def get_param(self, name: str) -> Any:
        """Return a parameter of the master's parameter server."""
        try:
            value = await self.node.master_call("getParam", name)
        except MasterError as exc:
            if "not set" in str(exc):
                raise KeyError(name) from None
            raise BridgeError(str(exc)) from None
        return _plain_xmlrpc(value)

    async def get_params(self, names: list[str] | None) -> dict[str, Any]:
        """Return the values of the parameters named that are set, or of every one (leaves) when None."""
        if names is None:
            return dict(_leaves("", await self.get_param("/")))

        async def one(name: str) -> tuple[str, Any] | None:
            try:
                return name, await self.get_param(name)
            except KeyError:
                return None

        return dict(found for found in await asyncio.gather(*(one(name) for name in names)) if found is not None)

    async def set_param(self, name: str, value: Any) -> None:
        """Set a parameter (XML-RPC has no null: a null value is refused)."""
        if _has_null(value):
            raise BridgeError(f"{name}: a ROS 1 parameter cannot hold null")
        await self._master("setParam", name, value)

    async def delete_param(self, name: str) -> None:
        """Delete a parameter."""
        try:
            await self.node.master_call("deleteParam", name)
        except MasterError as exc:
            if "not set" in str(exc):
                raise KeyError(name) from None
            raise BridgeError(str(exc)) from None

    async def param_names(self) -> list[str]:
        """Return every parameter's name."""
        return list(await self._master("getParamNames"))

    async def simulated_clock(self) -> bool:
        """Return whether /use_sim_time is set true: the graph's nodes then follow /clock."""
        try:
            return await self.get_param("/use_sim_time") is True
        except KeyError:
            return False

    # ------------------------------------------------------------------ actions

    async def action_servers(self) -> dict[str, str]:
        """Return the actionlib servers (their status, feedback and result topics published), with their types."""
        topics = await self.published_topics()
        servers = {}
        for topic, type_ in topics.items():
            namespace = topic.removesuffix("/status")
            result = topics.get(namespace + "/result", "")
            if type_ == "actionlib_msgs/GoalStatusArray" and namespace + "/feedback" in topics and result:
                servers[namespace] = result.removesuffix("Result")
        return servers

    async def send_action_goal(
        self,
        name: str,
        type_: str | None,
        goal: dict[str, Any],
        feedback: Callable[[dict[str, Any]], None] | None,
        timeout: float,
    ) -> Any:
        """Refuse: ROS 1 has no actions of ROS 2's form."""
        raise GoalOutcome(
            "this robot's graph is ROS 1, which has no ROS 2 actions: drive an actionlib server "
            f"through its topics ({name}/goal, {name}/cancel, {name}/feedback, {name}/result) instead"
        )

    def now(self) -> tuple[int, int]:
        """Return the wall-clock time (the bridge does not follow /clock)."""
        stamp = time.time_ns()
        return stamp // 1_000_000_000, stamp % 1_000_000_000

    def time_message(self, seconds: int, nanoseconds: int) -> dict[str, int]:
        """Return ROS 1's spelling of a time."""
        return {"secs": seconds, "nsecs": nanoseconds}

    def message_details(self, type_: str) -> list[dict[str, Any]]:
        """Return rosapi's TypeDefs of a message type."""
        return self.types.message_details(type_)

    def schema(self, type_: str) -> str:
        """Return a message type's full definition, as a ROS 1 publisher announces it."""
        return self.types.definition(type_)[0]

    def service_schemas(self, type_: str) -> tuple[str, str]:
        """Return the full definitions of a service's request and response."""
        request, response = self.types.ensure_service(type_)
        store = self.types.store
        return store.generate_msgdef(request, ros_version=1)[0], store.generate_msgdef(response, ros_version=1)[0]


def _plain_xmlrpc(value: Any) -> Any:
    if isinstance(value, xmlrpc.client.Binary):
        return value.data
    if isinstance(value, dict):
        return {key: _plain_xmlrpc(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_plain_xmlrpc(item) for item in value]
    return value


def _leaves(prefix: str, value: Any) -> list[tuple[str, Any]]:
    if not isinstance(value, dict):
        return [(prefix, value)]
    return [leaf for key, item in value.items() for leaf in _leaves(f"{prefix}/{key}", item)]


def _has_null(value: Any) -> bool:
    if value is None:
        return True
    if isinstance(value, dict):
        return any(_has_null(item) for item in value.values())
    if isinstance(value, list):
        return any(_has_null(item) for item in value)
    return False
