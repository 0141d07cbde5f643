"""The Foxglove WebSocket protocol's (v1) frames: subprotocols, opcodes, advertisements, and field checks."""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from bridgeos_agent.bridges.graph import BridgeError

__all__ = [
    "ERROR",
    "INFO",
    "SUBPROTOCOLS",
    "TIME",
    "WARNING",
    "Channel",
    "Fail",
    "Service",
    "encode",
    "ident_field",
    "items_field",
    "json_default",
    "select_subprotocol",
]

# The Foxglove app offers foxglove.websocket.v1; the Foxglove SDK's clients offer foxglove.sdk.v1 for
# the same messages. A door (or the cloud relay) answers with the one the client offered first.
SUBPROTOCOLS = ("foxglove.websocket.v1", "foxglove.sdk.v1")
MAX_ID = 2**32 - 1

# Binary opcodes: from the server, and from the client.
MESSAGE_DATA = 0x01
TIME = 0x02
SERVICE_CALL_RESPONSE = 0x03
CLIENT_MESSAGE_DATA = 0x01
SERVICE_CALL_REQUEST = 0x02

INFO, WARNING, ERROR = 0, 1, 2


def select_subprotocol(offered: Iterable[str]) -> str | None:
    """Return the first subprotocol a client offers that this protocol speaks, or None."""
    return next((name for name in offered if name in SUBPROTOCOLS), None)


def encode(message: dict[str, Any]) -> str:
    """Encode a JSON protocol message."""
    return json.dumps(message, separators=(",", ":"))


class Fail(BridgeError):
    """A client's request that is refused, at a level (error unless said)."""

    def __init__(self, message: str, level: int = ERROR) -> None:
        super().__init__(message)
        self.level = level


def ident_field(value: Any, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= MAX_ID:
        raise Fail(f"{what} must be an integer in 0..{MAX_ID}, not {value!r}"[:200])
    return value


def items_field(message: dict[str, Any], key: str) -> list[Any]:
    value = message.get(key)
    if not isinstance(value, list):
        raise Fail(f"'{key}' must be an array" if key in message else f"'{key}' is missing")
    return value


@dataclass
class Channel:
    """A topic of the graph offered to clients."""

    id: int
    topic: str
    type: str
    encoding: str
    schema_encoding: str
    schema: str

    def advertisement(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "topic": self.topic,
            "encoding": self.encoding,
            "schemaName": self.type,
            "schemaEncoding": self.schema_encoding,
            "schema": self.schema,
        }


@dataclass
class Service:
    """A service of the graph offered to clients."""

    id: int
    name: str
    type: str
    encoding: str
    schema_encoding: str
    schemas: tuple[str, str]

    def advertisement(self) -> dict[str, Any]:
        def part(suffix: str, schema: str) -> dict[str, str]:
            return {
                "encoding": self.encoding,
                "schemaName": self.type + suffix,
                "schemaEncoding": self.schema_encoding,
                "schema": schema,
            }

        return {
            "id": self.id,
            "name": self.name,
            "type": self.type,
            "request": part("_Request", self.schemas[0]),
            "response": part("_Response", self.schemas[1]),
            # Older clients read only these; the schema encoding is then taken from supportedEncodings.
            "requestSchema": self.schemas[0],
            "responseSchema": self.schemas[1],
        }


def json_default(value: Any) -> Any:
    if isinstance(value, bytes | bytearray | memoryview):
        return list(bytes(value))
    raise TypeError(f"{type(value).__name__} is not JSON serializable")
