"""rosbridge v2's frames: their two encodings, and the checks of a client's fields that name what is wrong."""

from __future__ import annotations

import base64
import json
import math
from typing import Any

from bridgeos_agent.bridges.graph import BridgeError

__all__ = [
    "COMPRESSIONS",
    "LEVELS",
    "Fail",
    "count_field",
    "encode_cbor",
    "encode_json",
    "json_default",
    "name_field",
    "text_field",
]

LEVELS = {"info": 0, "warning": 1, "error": 2, "none": 3}
COMPRESSIONS = ("none", "cbor", "cbor-raw")


def json_default(value: Any) -> Any:
    # rosbridge sends uint8[]/char[] as base64 in JSON; numeric arrays arrive as lists already.
    if isinstance(value, bytes | bytearray | memoryview):
        return base64.b64encode(value).decode()
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def encode_json(message: dict[str, Any]) -> str:
    """Encode a protocol message as rosbridge's JSON."""
    return json.dumps(message, default=json_default, separators=(",", ":"))


def encode_cbor(message: dict[str, Any]) -> bytes:
    """Encode a protocol message as CBOR (byte arrays stay bytes)."""
    import cbor2

    return cbor2.dumps(message)


class Fail(BridgeError):
    """A client's request that is refused, at a level (error unless said)."""

    def __init__(self, message: str, level: str = "error") -> None:
        super().__init__(message)
        self.level = level


def text_field(message: dict[str, Any], key: str, *, required: bool = True) -> str | None:
    value = message.get(key)
    if value is None and not required:
        return None
    if not isinstance(value, str) or not value:
        raise Fail(f"'{key}' must be a non-empty string" if key in message else f"'{key}' is missing")
    return value


def name_field(message: dict[str, Any], key: str) -> str:
    value = text_field(message, key)
    assert value is not None
    if len(value) > 256 or any(ch.isspace() for ch in value):
        raise Fail(f"'{key}' {value[:64]!r} is not a ROS name")
    return value if value.startswith("/") else "/" + value


def count_field(message: dict[str, Any], key: str, default: int, *, upto: int | None = None) -> int:
    value = message.get(key, default)
    if value is None:
        return default
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
        raise Fail(f"'{key}' must be a number >= 0, not {value!r}")
    if upto is not None and value > upto:
        raise Fail(f"'{key}' must be at most {upto}, not {value!r}")
    return int(value)


def fragments(frame: str, size: int, ident: str) -> list[str]:
    """Split a JSON frame into rosbridge ``fragment`` frames of at most ``size`` characters of it each."""
    total = -(-len(frame) // size)
    return [
        encode_json({"op": "fragment", "id": ident, "data": frame[i * size : (i + 1) * size], "num": i, "total": total})
        for i in range(total)
    ]
