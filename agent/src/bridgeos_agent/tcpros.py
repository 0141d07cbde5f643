"""Encode and decode the ROS 1 TCPROS wire format: connection headers, message frames, statistics.

Pure functions over bytes, no sockets: the Skill Router forwards message frames as they
arrive (a 4-byte little-endian length, then the serialized message) without decoding them.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from dataclasses import dataclass

__all__ = [
    "MAX_HEADER_BYTES",
    "MAX_MESSAGE_BYTES",
    "TOPIC_STATISTICS_DEFINITION",
    "TOPIC_STATISTICS_MD5",
    "TOPIC_STATISTICS_TYPE",
    "HeaderError",
    "TopicStatistics",
    "decode_header",
    "encode_header",
    "frame",
    "header_stamp",
    "split_frames",
]

MAX_HEADER_BYTES = 1 << 20
# A frame larger than this is a broken peer, not a pointcloud (ROS's own limit is 1 GB).
MAX_MESSAGE_BYTES = 512 << 20

_U32 = struct.Struct("<I")
_STAMP = struct.Struct("<II")


class HeaderError(ValueError):
    """A TCPROS connection header that cannot be read."""


def encode_header(fields: Mapping[str, str]) -> bytes:
    """Return a connection header: its length, then each ``key=value`` field with its length."""
    parts = []
    for key, value in fields.items():
        item = f"{key}={value}".encode()
        parts.append(_U32.pack(len(item)))
        parts.append(item)
    body = b"".join(parts)
    return _U32.pack(len(body)) + body


def decode_header(body: bytes) -> dict[str, str]:
    """Return the fields of a connection header body (without its leading length)."""
    fields: dict[str, str] = {}
    offset, end = 0, len(body)
    while offset < end:
        if offset + 4 > end:
            raise HeaderError("truncated field length")
        (size,) = _U32.unpack_from(body, offset)
        offset += 4
        if offset + size > end:
            raise HeaderError("field runs past the end of the header")
        item = body[offset : offset + size].decode("utf-8", "replace")
        offset += size
        key, sep, value = item.partition("=")
        if not sep:
            raise HeaderError(f"field without '=': {item[:40]!r}")
        fields[key] = value
    return fields


def frame(payload: bytes) -> bytes:
    """Return one message frame: its length, then the serialized message."""
    return _U32.pack(len(payload)) + payload


def split_frames(buffer: bytes | bytearray, start: int = 0) -> tuple[int, int]:
    """Find the complete frames in ``buffer`` from ``start``; return (end of the last one, how many)."""
    offset, count, end = start, 0, len(buffer)
    unpack = _U32.unpack_from
    while offset + 4 <= end:
        (size,) = unpack(buffer, offset)
        if size > MAX_MESSAGE_BYTES:
            raise HeaderError(f"message of {size} bytes exceeds the {MAX_MESSAGE_BYTES} byte limit")
        if offset + 4 + size > end:
            break
        offset += 4 + size
        count += 1
    return offset, count


def header_stamp(buffer: bytes | bytearray, offset: int) -> float | None:
    """Return the ``header.stamp`` (s) of the framed message at ``offset`` whose type starts with a Header."""
    if offset + 16 > len(buffer):
        return None
    secs, nsecs = _STAMP.unpack_from(buffer, offset + 8)  # after the frame length and header.seq
    return secs + nsecs * 1e-9


# rosgraph_msgs/TopicStatistics, as Debian's rosgraph_msgs defines it.
TOPIC_STATISTICS_TYPE = "rosgraph_msgs/TopicStatistics"
TOPIC_STATISTICS_MD5 = "10152ed868c5097a5e2e4a89d7daa710"
TOPIC_STATISTICS_DEFINITION = """# name of the topic
string topic

# node id of the publisher
string node_pub

# node id of the subscriber
string node_sub

# the statistics apply to this time window
time window_start
time window_stop

# number of messages delivered during the window
int32 delivered_msgs
# numbers of messages dropped during the window
int32 dropped_msgs

# traffic during the window, in bytes
int32 traffic

# mean/stddev/max period between two messages
duration period_mean
duration period_stddev
duration period_max

# mean/stddev/max age of the message based on the
# timestamp in the message header. In case the
# message does not have a header, it will be 0.
duration stamp_age_mean
duration stamp_age_stddev
duration stamp_age_max
"""

_INT32_MAX = 2**31 - 1


def _string(value: str) -> bytes:
    data = value.encode()
    return _U32.pack(len(data)) + data


def _time(seconds: float) -> bytes:
    secs = int(seconds)
    return struct.pack("<II", max(0, secs), max(0, min(999_999_999, round((seconds - secs) * 1e9))))


def _duration(seconds: float) -> bytes:
    nanos = round(seconds * 1e9)
    secs, nsecs = divmod(nanos, 1_000_000_000)  # ROS keeps nsecs in [0, 1e9)
    return struct.pack("<ii", max(-_INT32_MAX - 1, min(_INT32_MAX, secs)), nsecs)


@dataclass(frozen=True, slots=True)
class TopicStatistics:
    """One window of a topic's statistics, as ``rosgraph_msgs/TopicStatistics`` carries it."""

    topic: str
    node_pub: str
    node_sub: str
    window_start: float
    window_stop: float
    delivered_msgs: int
    dropped_msgs: int
    traffic: int
    period_mean: float = 0.0
    period_stddev: float = 0.0
    period_max: float = 0.0
    stamp_age_mean: float = 0.0
    stamp_age_stddev: float = 0.0
    stamp_age_max: float = 0.0

    def serialize(self) -> bytes:
        """Return the message serialized the way genpy does (without a frame length)."""

        def clamp(value: int) -> int:
            return max(0, min(_INT32_MAX, value))

        return b"".join(
            (
                _string(self.topic),
                _string(self.node_pub),
                _string(self.node_sub),
                _time(self.window_start),
                _time(self.window_stop),
                struct.pack("<iii", clamp(self.delivered_msgs), clamp(self.dropped_msgs), clamp(self.traffic)),
                _duration(self.period_mean),
                _duration(self.period_stddev),
                _duration(self.period_max),
                _duration(self.stamp_age_mean),
                _duration(self.stamp_age_stddev),
                _duration(self.stamp_age_max),
            )
        )
