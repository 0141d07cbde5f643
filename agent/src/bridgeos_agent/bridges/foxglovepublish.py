"""The Foxglove WebSocket ``clientPublish`` capability: a client's channels, published in the robot's graph."""

from __future__ import annotations

import json
import struct
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from bridgeos_agent.bridges.foxglovewire import ERROR, WARNING, Fail, ident_field, items_field
from bridgeos_agent.bridges.graph import BridgeError, GraphPublisher

if TYPE_CHECKING:
    from bridgeos_agent.bridges.foxglove import FoxgloveSession

__all__ = ["MAX_CLIENT_CHANNELS", "ClientChannels"]

MAX_CLIENT_CHANNELS = 256  # channels one client may advertise


@dataclass
class _ClientChannel:
    """A channel a client advertised: where its messages go, and how they are encoded."""

    topic: str
    encoding: str
    publisher: GraphPublisher
    published: int = field(default=0)


class ClientChannels:
    """The channels one client advertised, each a publisher in the graph shared with other clients of the topic."""

    def __init__(self, session: FoxgloveSession) -> None:
        self.session = session
        self._channels: dict[int, _ClientChannel] = {}

    def handlers(self) -> dict[str, Callable[[dict[str, Any]], Awaitable[None]]]:
        """Return the session's handlers of advertise and unadvertise."""
        return {"advertise": self.advertise, "unadvertise": self.unadvertise}

    async def advertise(self, message: dict[str, Any]) -> None:
        """Publish in the graph on each channel the client advertises."""
        for item in items_field(message, "channels"):
            try:
                await self._advertise_one(item)
            except BridgeError as exc:
                self.session.status(getattr(exc, "level", ERROR), f"advertise: {exc}")

    async def _advertise_one(self, item: Any) -> None:
        if not isinstance(item, dict):
            raise Fail("each channel must be an object with 'id', 'topic', 'encoding' and 'schemaName'")
        ident = ident_field(item.get("id"), "a channel's 'id'")
        topic, encoding, type_ = item.get("topic"), item.get("encoding"), item.get("schemaName")
        for key, value in (("topic", topic), ("encoding", encoding), ("schemaName", type_)):
            if not isinstance(value, str) or not value:
                raise Fail(f"channel {ident}: '{key}' must be a non-empty string")
        assert isinstance(topic, str) and isinstance(encoding, str) and isinstance(type_, str)
        if len(topic) > 256 or any(ch.isspace() for ch in topic):
            raise Fail(f"channel {ident}: {topic[:64]!r} is not a ROS topic name")
        topic = topic if topic.startswith("/") else "/" + topic
        if encoding not in self.session.bridge.encodings:
            raise Fail(
                f"channel {ident}: encoding {encoding[:32]!r} is not one of {', '.join(self.session.bridge.encodings)}"
            )
        if ident in self._channels:
            raise Fail(f"channel id {ident} is already advertised by this client")
        if len(self._channels) >= MAX_CLIENT_CHANNELS:
            raise Fail(f"a client may advertise at most {MAX_CLIENT_CHANNELS} channels")
        publisher = await self.session.bridge.publishers.advertise(topic, type_, (self.session, ident))
        self._channels[ident] = _ClientChannel(topic, encoding, publisher)

    async def unadvertise(self, message: dict[str, Any]) -> None:
        """Stop publishing the client's channels named."""
        for value in items_field(message, "channelIds"):
            try:
                ident = ident_field(value, "a channel id")
                channel = self._channels.pop(ident, None)
                if channel is None:
                    raise Fail(f"channel {ident} is not advertised by this client", WARNING)
                self.session.bridge.publishers.unadvertise(channel.topic, (self.session, ident))
            except Fail as exc:
                self.session.status(exc.level, f"unadvertise: {exc}")

    async def message(self, data: bytes) -> None:
        """Publish one client message data frame (opcode, channel id, payload) on its channel's topic."""
        if len(data) < 5:
            raise Fail(f"{len(data)} bytes: too short for a channel id")
        (ident,) = struct.unpack_from("<I", data, 1)
        channel = self._channels.get(ident)
        if channel is None:
            raise Fail(f"channel {ident} is not advertised by this client")
        payload = data[5:]
        if channel.encoding == "json":
            try:
                msg = json.loads(payload)
            except ValueError as exc:
                raise Fail(f"{channel.topic}: the message is not JSON: {exc}") from None
            if not isinstance(msg, dict):
                raise Fail(f"{channel.topic}: a JSON message must be an object")
            channel.publisher.publish(msg)
        else:
            try:
                channel.publisher.publish_raw(payload)
            except BridgeError as exc:
                raise Fail(f"{channel.topic}: {exc}") from None
        channel.published += 1

    def close(self) -> None:
        """Stop publishing every channel of the client."""
        for ident, channel in list(self._channels.items()):
            self.session.bridge.publishers.unadvertise(channel.topic, (self.session, ident))
        self._channels.clear()
