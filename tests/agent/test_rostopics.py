"""A subscription's TCPROS connection over a real socket: frames handed on whole, however they arrive."""

from __future__ import annotations

import asyncio
import itertools
import os
import socket
import subprocess
import sys

from bridgeos_agent.rosnode import RosNode
from bridgeos_agent.rostopics import Inbound, Subscription, iter_frames, read_header
from bridgeos_agent.tcpros import encode_header, frame
from tests.agent.roshelpers import private_rosmaster


async def _connected(received: list[tuple[bytes, int]]) -> tuple[Inbound, asyncio.StreamReader, asyncio.StreamWriter]:
    """Connect an Inbound to a publisher played by the test over a socket pair; exchange headers."""
    node = RosNode("/test_inbound", "http://127.0.0.1:9")
    subscription = Subscription(
        node, "/cloud", "sensor_msgs/PointCloud2", lambda s, blob, n, i: received.append((blob, n))
    )
    ours, theirs = socket.socketpair()
    _, inbound = await asyncio.get_running_loop().create_connection(
        lambda: Inbound(subscription, "http://publisher:1/"), sock=ours
    )
    reader, writer = await asyncio.open_connection(sock=theirs)
    request = await read_header(reader)
    assert request["topic"] == "/cloud"
    writer.write(encode_header({"callerid": "/publisher", "md5sum": "*", "type": "sensor_msgs/PointCloud2"}))
    return inbound, reader, writer


async def _frames(received: list[tuple[bytes, int]], count: int) -> list[bytes]:
    """Wait until ``count`` frames were handed on; return them one by one."""
    async with asyncio.timeout(30):
        while sum(n for _, n in received) < count:
            await asyncio.sleep(0.01)
    return [f for blob, _ in received for f in iter_frames(blob)]


async def test_a_35_mb_message_in_many_reads_is_handed_on_once_and_whole() -> None:
    received: list[tuple[bytes, int]] = []
    inbound, _, writer = await _connected(received)
    big = frame(bytes(range(256)) * ((35 << 20) // 256))
    small = frame(b"after")
    stream = big + small
    # A length prefix cut in two, then the body in many reads.
    cuts = [0, 2, *range(1 << 16, len(stream), 1 << 16), len(stream)]
    for start, end in itertools.pairwise(cuts):
        writer.write(stream[start:end])
        await writer.drain()
        await asyncio.sleep(0)
    frames = await _frames(received, 2)
    assert frames == [big, small]
    assert all(n >= 1 for _, n in received) and len(received) <= 2
    assert inbound.header is not None and inbound.header["callerid"] == "/publisher"
    writer.close()


async def test_frames_cut_anywhere_arrive_in_order_and_whole() -> None:
    received: list[tuple[bytes, int]] = []
    _, _, writer = await _connected(received)
    messages = [frame(bytes([i]) * (i * 37)) for i in range(1, 60)]
    stream = b"".join(messages)
    for start in range(0, len(stream), 7):
        writer.write(stream[start : start + 7])
        await writer.drain()
        await asyncio.sleep(0)
    assert await _frames(received, len(messages)) == messages
    writer.close()


BIND_CHECK = """
import asyncio, os, sys
from bridgeos_agent.rosnode import RosNode

async def main():
    node = RosNode("/test_bind", sys.argv[1], host="127.0.0.2")  # not loopback to the node: binds wide
    await node.start()
    try:
        assert node.uri.startswith("http://127.0.0.2:"), node.uri
        assert await node._xmlrpc(node.uri, "getPid", ("/test",)) == [1, "", os.getpid()]
        _, writer = await asyncio.open_connection("127.0.0.2", node.tcpros_port)
        writer.close()
    finally:
        await node.close()

asyncio.run(main())
"""


def test_a_node_on_a_non_loopback_address_answers_on_the_ports_it_advertises(tmp_path) -> None:
    # Bound to every address, IPv4 and IPv6 got a port each and either could be advertised: asyncio
    # orders them through a set, so which one depends on the hash seed. Eight seeds cover both orders.
    with private_rosmaster(tmp_path) as master:
        for seed in range(8):
            done = subprocess.run(
                [sys.executable, "-c", BIND_CHECK, master],
                env={**os.environ, "PYTHONHASHSEED": str(seed)},
                capture_output=True,
                text=True,
                timeout=60,
            )
            assert done.returncode == 0, f"PYTHONHASHSEED={seed}: {done.stderr[-2000:]}"
