"""bridges.py's WebSocket clients: rosbridge and Foxglove viewers, what they count, and a rosbridge publisher."""

from __future__ import annotations

import asyncio
import json
import struct
import subprocess
import sys
import time
from typing import Any


async def open_client(url: str, headers: dict[str, str] | None = None, subprotocols: list[str] | None = None) -> Any:
    """Open a WebSocket client to a door, without compression, pings or a size limit."""
    from websockets.asyncio.client import connect

    return await connect(
        url,
        additional_headers=headers,
        subprotocols=subprotocols,  # type: ignore[arg-type]
        max_size=None,
        open_timeout=15,
        close_timeout=1,  # a viewer leaving a flood does not wait for the cloud to drain its queue
        ping_interval=None,
        compression=None,
    )


async def rosbridge_subscribe(url: str, headers: dict[str, str] | None, topic: str) -> Any:
    """Open a rosbridge client subscribed to a topic of std_msgs/String."""
    websocket = await open_client(url, headers)
    await websocket.send(
        json.dumps({"op": "subscribe", "topic": topic, "type": "std_msgs/String", "queue_length": 1000})
    )
    return websocket


async def foxglove_subscribe(url: str, headers: dict[str, str] | None, topic: str, timeout: float = 20) -> Any:
    """Open a Foxglove client and subscribe to a topic's channel once the server advertises it."""
    websocket = await open_client(url, headers, ["foxglove.websocket.v1"])
    deadline = time.monotonic() + timeout
    while True:
        frame = await asyncio.wait_for(websocket.recv(), max(0.1, deadline - time.monotonic()))
        if isinstance(frame, str):
            message = json.loads(frame)
            if message.get("op") == "advertise":
                for channel in message["channels"]:
                    if channel["topic"] == topic:
                        subscribe = {"op": "subscribe", "subscriptions": [{"id": 1, "channelId": channel["id"]}]}
                        await websocket.send(json.dumps(subscribe))
                        return websocket


def string_seq_stamp(frame: str | bytes, kind: str) -> tuple[int, float]:
    """Return a talker string's (seq, stamp) from a rosbridge JSON frame or a Foxglove binary one."""
    if kind == "rosbridge":
        data = json.loads(frame)["msg"]["data"]
    else:
        assert isinstance(frame, bytes)
        # opcode, subscription id, timestamp, then ROS 1's String: a length and the bytes.
        (length,) = struct.unpack_from("<I", frame, 13)
        data = frame[17 : 17 + length].decode()
    seq, stamp, _ = data.split(" ", 2)
    return int(seq), float(stamp)


async def count_messages(websocket: Any, kind: str, warmup: float, seconds: float) -> float:
    """Return the messages/s a client receives over ``seconds`` after ``warmup``."""
    counted = 0
    started = time.monotonic()
    begin = started + warmup
    end = begin + seconds
    while True:
        now = time.monotonic()
        if now >= end:
            break
        try:
            frame = await asyncio.wait_for(websocket.recv(), end - now)
        except TimeoutError:
            break
        is_message = (isinstance(frame, bytes) and frame[:1] == b"\x01") if kind == "foxglove" else '"publish"' in frame
        if is_message and time.monotonic() >= begin:
            counted += 1
    return counted / seconds


async def stamps(websocket: Any, kind: str, seconds: float, arrivals: dict[int, float]) -> None:
    """Record each message's latency (arrival minus the talker's stamp) by its sequence number."""
    end = time.monotonic() + seconds
    while (left := end - time.monotonic()) > 0:
        try:
            frame = await asyncio.wait_for(websocket.recv(), left)
        except TimeoutError:
            break
        if kind == "rosbridge" and '"publish"' not in frame:
            continue
        if kind == "foxglove" and not (isinstance(frame, bytes) and frame[:1] == b"\x01"):
            continue
        arrived = time.time()
        seq, stamp = string_seq_stamp(frame, kind)
        arrivals[seq] = (arrived - stamp) * 1000


# A rosbridge client publishing 100-byte strings flat out for a while, in a process of its own so the
# subscriber it is measured by does not share its event loop; it writes its frames a hundred to a
# send, built ahead, so what is measured is the door and not the publisher's own Python. It prints
# how many it sent while counted.
PUBLISHER = r"""
import json, sys, time
from websockets.frames import Frame, Opcode
from websockets.sync.client import connect
url, warmup, seconds = sys.argv[1], float(sys.argv[2]), float(sys.argv[3])

def frame(seq):
    head = "%d %.6f " % (seq, time.time())
    text = json.dumps({"op": "publish", "topic": "/b2b", "msg": {"data": head + "x" * (100 - len(head))}})
    return Frame(Opcode.TEXT, text.encode()).serialize(mask=True, extensions=[])

with connect(url, max_size=None, compression=None) as ws:
    ws.send(json.dumps({"op": "advertise", "topic": "/b2b", "type": "std_msgs/String"}))
    time.sleep(0.5)
    start = time.monotonic()
    counted = seq = 0
    while (now := time.monotonic()) < start + warmup + seconds:
        burst = b"".join(frame(seq + i) for i in range(1, 101))
        seq += 100
        ws.socket.sendall(burst)
        counted += 100 * (now >= start + warmup)
print(counted, flush=True)
"""


async def bridge_to_bridge(url: str, warmup: float, seconds: float) -> tuple[float, float]:
    """Return the msgs/s one rosbridge client hears of another's flat-out publishing, and the share delivered."""
    subscriber = await rosbridge_subscribe(url, None, "/b2b")
    publisher = await asyncio.create_subprocess_exec(
        sys.executable, "-c", PUBLISHER, url, str(warmup + 0.5), str(seconds), stdout=subprocess.PIPE
    )
    try:
        rate = await count_messages(subscriber, "rosbridge", warmup + 1.0, seconds)
        out, _ = await asyncio.wait_for(publisher.communicate(), 30)
    finally:
        if publisher.returncode is None:
            publisher.kill()
            await publisher.wait()
        await subscriber.close()
    sent = int(out or 0)
    return rate, min(1.0, rate * seconds / sent) if sent else 0.0


async def cloud_lags(websocket: Any, seconds: float, warmup: float, lags: list[float]) -> int:
    """Record each point cloud's lag (arrival minus its header stamp, ms); return how many arrived."""
    start = time.monotonic()
    received = 0
    while (left := start + warmup + seconds - time.monotonic()) > 0:
        try:
            frame = await asyncio.wait_for(websocket.recv(), left)
        except TimeoutError:
            break
        if not (isinstance(frame, bytes) and frame[:1] == b"\x01"):
            continue
        arrived = time.time()
        if time.monotonic() < start + warmup:
            continue
        _, secs, nsecs = struct.unpack_from("<III", frame, 13)  # the header after the 13-byte Foxglove head
        lags.append((arrived - (secs + nsecs / 1e9)) * 1000)
        received += 1
    return received
