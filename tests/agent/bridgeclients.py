"""Bridge clients as a robot's users run them, each seen the same way: publish a topic, hear a topic.

Two real third-party clients stand behind one small interface, so a test can put any of them on
either end of a topic: roslibpy (rosbridge v2) and @foxglove/ws-protocol (Foxglove WebSocket, in
Node). A message is the std_msgs/String "tag seq stamp" that the rospy and rclpy test nodes also
print, so a ROS node can sit on either end too.
"""

from __future__ import annotations

import base64
import queue
import threading
import time
from collections.abc import Callable
from typing import Any

import roslibpy

from tests.agent.foxgloveclient import FoxgloveClient

__all__ = ["FoxgloveSide", "RosbridgeSide", "text"]


def text(tag: str, seq: int) -> str:
    """Return the message text the test nodes print back as 'tag seq'."""
    return f"{tag} {seq} {time.time():.6f}"


class RosbridgeSide:
    """A roslibpy client: one connection, any number of topics published and subscribed."""

    def __init__(self, ros: roslibpy.Ros, name: str) -> None:
        self.ros = ros
        self.name = name
        self._topics: dict[str, roslibpy.Topic] = {}
        self._heard: dict[str, list[str]] = {}
        self._lock = threading.Lock()

    def subscribe(self, topic: str) -> None:
        heard = self._heard.setdefault(topic, [])
        subscriber = roslibpy.Topic(self.ros, topic, "std_msgs/String")

        def received(message: dict[str, Any]) -> None:
            with self._lock:
                heard.append(message["data"])

        subscriber.subscribe(received)

    def advertise(self, topic: str) -> None:
        publisher = self._topics[topic] = roslibpy.Topic(self.ros, topic, "std_msgs/String")
        publisher.advertise()

    def publish(self, topic: str, data: str) -> None:
        self._topics[topic].publish(roslibpy.Message({"data": data}))

    def heard(self, topic: str) -> list[str]:
        with self._lock:
            return list(self._heard.get(topic, []))

    def close(self) -> None:
        self.ros.close()


class FoxgloveSide:
    """An @foxglove/ws-protocol client: subscribes to advertised channels, publishes with clientPublish."""

    def __init__(self, client: FoxgloveClient, name: str, ros: str) -> None:
        self.client = client
        self.name = name
        self.ros = ros
        self.encoding = "ros1" if ros == "ros1" else "cdr"
        self.type = "std_msgs/String" if ros == "ros1" else "std_msgs/msg/String"
        self._channels: dict[str, int] = {}  # topic -> our client channel id
        self._subscriptions: dict[int, str] = {}  # subscription id -> topic
        self._decoders: dict[str, Callable[[bytes], Any]] = {}
        self._heard: dict[str, list[str]] = {}
        self._encode: Callable[[dict[str, Any]], bytes] | None = None

    def subscribe(self, topic: str) -> None:
        channel = self.client.channel(topic, timeout=30)
        self._decoders[topic] = _decoder(self.ros, channel["schemaName"], channel["schema"])
        self.client.command("subscribe", topic=topic)
        subscribed = self.client.wait("subscribed", lambda e: e["topic"] == topic)
        self._subscriptions[subscribed["subscriptionId"]] = topic
        self._heard.setdefault(topic, [])

    def advertise(self, topic: str, schema: str) -> None:
        self.client.command("advertise", topic=topic, encoding=self.encoding, schemaName=self.type)
        self._channels[topic] = self.client.wait("advertised", lambda e: e["topic"] == topic)["channelId"]
        self._encode = _encoder(self.ros, self.type, schema)

    def publish(self, topic: str, data: str) -> None:
        assert self._encode is not None
        raw = self._encode({"data": data})
        self.client.command("publish", channelId=self._channels[topic], data=base64.b64encode(raw).decode())

    def heard(self, topic: str) -> list[str]:
        self._drain()
        return list(self._heard.get(topic, []))

    def _drain(self) -> None:
        while True:
            try:
                event = self.client.events.get_nowait()
            except queue.Empty:
                return
            subscribed = (
                self._subscriptions.get(event.get("subscriptionId", -1)) if event["event"] == "message" else None
            )
            if subscribed is None:
                self.client.seen.append(event)
                continue
            message = self._decoders[subscribed](base64.b64decode(event["data"]))
            self._heard[subscribed].append(message["data"] if isinstance(message, dict) else message.data)

    def close(self) -> None:
        self.client.close()


def _decoder(ros: str, schema_name: str, schema: str) -> Callable[[bytes], Any]:
    """Return a decoder built from an advertised schema alone, as a Foxglove client builds one."""
    if ros == "ros1":
        from mcap_ros1._vendor.genpy.dynamic import generate_dynamic as ros1_dynamic

        cls = ros1_dynamic(schema_name, schema)[schema_name]
        return lambda raw: cls().deserialize(raw)
    from mcap_ros2._dynamic import generate_dynamic as ros2_dynamic

    return ros2_dynamic(schema_name, schema)[schema_name]


def _encoder(ros: str, schema_name: str, schema: str) -> Callable[[dict[str, Any]], bytes]:
    """Return an encoder built from a schema alone, as a Foxglove client publishes with one."""
    if ros == "ros1":
        import io

        from mcap_ros1._vendor.genpy.dynamic import generate_dynamic as ros1_dynamic

        cls = ros1_dynamic(schema_name, schema)[schema_name]

        def encode(fields: dict[str, Any]) -> bytes:
            buffer = io.BytesIO()
            cls(**fields).serialize(buffer)
            return buffer.getvalue()

        return encode
    from mcap_ros2._dynamic import serialize_dynamic

    return serialize_dynamic(schema_name, schema)[schema_name]
