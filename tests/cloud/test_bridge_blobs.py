"""A large frame several bridge clients receive crosses the robot's link once (a blob), not once per client.

The agent and the cloud count the same window of blobs, so the agent sends again a blob the cloud
no longer holds; through a real daphne, a real agent and real ROS 1, five clients of a 150 kB topic
(Foxglove clients with subscription ids of their own, roslibpy clients) get whole, correct
messages while the link carries about one copy of each.
"""

from __future__ import annotations

import asyncio
import base64
import json
import struct
import time
from collections.abc import Iterator
from typing import Any

import pytest
import roslibpy

from bridgeos_agent import protocol
from bridgeos_agent.bridges.fanout import SharedTail
from bridgeos_agent.bridges.relay import BridgeRelay
from bridgeos_agent.protocol import BlobWindow, Event
from robots.bridges import RobotBridges
from tests.cloud.test_bridge_relay import counters, raw, robot, ros, token_client, url
from tests.conftest import Server, another_daphne, wait_until

__all__ = ["robot", "ros"]  # test_bridge_relay's fixtures, on this module's own daphne

SIZE = 150_000  # bytes of padding in each /big message: well over the blob threshold


async def never(*_: Any) -> Any:
    raise AssertionError("no graph is needed here")


def test_the_agent_knows_which_blobs_the_cloud_holds_and_sends_a_pushed_out_one_again() -> None:
    sent: list[bytes] = []

    async def send_binary(message: bytes) -> None:
        sent.append(message)

    async def send_event(event: Event, data: dict[str, Any]) -> None:
        raise AssertionError("blobs travel as binary messages only")

    relay = BridgeRelay(send_event, never, send_binary=send_binary)
    relay.window = BlobWindow(count=2, size=1 << 30)
    cloud = RobotBridges("r")
    cloud.window = BlobWindow(count=2, size=1 << 30)
    first, second, third = b"a" * 70_000, b"b" * 70_000, "c" * 70_000
    big = bytes(range(256)) * 6_000  # 1.5 MB: two parts on the link

    async def scenario() -> list[int]:
        ids = [await relay.blob(first), await relay.blob(first)]  # the same object: sent once
        assert len(sent) == 1
        ids += [await relay.blob(second), await relay.blob(third)]  # pushes `first` out of the window
        ids.append(await relay.blob(first))  # so it is sent again, under a new id
        ids.append(await relay.blob(big))
        return ids

    ids = asyncio.run(scenario())
    assert ids[0] == ids[1] and len(set(ids)) == 5, ids
    assert len(sent) == 6  # first, second, third, first again, big in two parts
    for message in sent:
        cloud.take_blob(message)
    assert sorted(cloud.blobs) == sorted(relay.window.held) == [ids[4], ids[5]]
    assert cloud.blobs[ids[4]] == first and cloud.blobs[ids[5]] == big
    cloud.take_blob(protocol.encode_bridge_blob(9, third)[0])
    assert cloud.blobs[9] == third  # a text blob goes to its clients as text

    # A client's frame is its own head and the blob; one naming a blob that left is dropped, counted.
    frame = protocol.BridgeFrame(session="s" * 16, blob=9)
    assert cloud.blob_frame(frame) == {"type": "bridge.frame", "whole": third}
    head = struct.pack("<BIQ", 1, 42, 7)
    named = protocol.BridgeFrame(session="s" * 16, blob=ids[5], head=base64.b64encode(head).decode())
    assert cloud.blob_frame(named) == {"type": "bridge.frame", "whole": head + big}
    assert cloud.blob_frame(protocol.BridgeFrame(session="s" * 16, blob=ids[0])) is None
    assert cloud.dropped == 1

    # A shared frame is the whole frame to any door that does not look inside it.
    shared = SharedTail(head, memoryview(big))
    assert bytes(shared) == head + big and shared.tail.obj is big  # type: ignore[union-attr]


def test_two_clients_sending_large_blobs_at_once_do_not_interleave_their_parts() -> None:
    sent: list[bytes] = []

    async def send_binary(message: bytes) -> None:
        await asyncio.sleep(0)  # the link's writer lets other tasks run between messages
        sent.append(message)

    relay = BridgeRelay(never, never, send_binary=send_binary)
    one, two = b"1" * 2_500_000, b"2" * 2_500_000  # three parts each

    async def both() -> list[int]:
        return list(await asyncio.gather(relay.blob(one), relay.blob(two)))

    ids = asyncio.run(both())
    cloud = RobotBridges("r")
    for message in sent:
        cloud.take_blob(message)
    assert cloud.blobs == {ids[0]: one, ids[1]: two}


def test_a_malformed_blob_is_refused_with_the_reason_and_changes_nothing() -> None:
    cloud = RobotBridges("r")
    cloud.take_blob(protocol.encode_bridge_blob(1, b"x" * 100)[0])
    bad = [
        (b"\xb1BOB" + b"\x00", "not a bridge blob"),
        (protocol.encode_bridge_blob(2, b"x")[0][:8] + b"\x80" + b"x", "unknown bridge blob flags"),
        (protocol.encode_bridge_blob(3, b"x" * (protocol.BRIDGE_BLOB_PART_BYTES + 10))[0] + b"y" * 20, "at most"),
        (protocol.encode_bridge_blob(4, b"\xff\xfe")[0][:8] + b"\x01" + b"\xff\xfe", "not UTF-8"),
    ]
    for message, reason in bad:
        with pytest.raises(protocol.ProtocolError, match=reason):
            cloud.take_blob(message)
    first_part = protocol.encode_bridge_blob(5, b"x" * (protocol.BRIDGE_BLOB_PART_BYTES + 1))[0]
    cloud.take_blob(first_part)
    with pytest.raises(protocol.ProtocolError, match="began before blob 5 ended"):
        cloud.take_blob(protocol.encode_bridge_blob(6, b"y")[0])
    assert list(cloud.blobs) == [1]
    with pytest.raises(protocol.ValidationError):
        protocol.BridgeFrame(session="s" * 16, text="x", head="AAAA")  # a head belongs to a blob's frame
    with pytest.raises(protocol.ValidationError):
        protocol.BridgeFrame(session="s" * 16, blob=1, more=True)


@pytest.fixture(scope="module")
def cloud(django_db_setup, django_db_blocker, tmp_path_factory) -> Iterator[Server]:
    # The cloud's own per-client defaults (16 MiB/s): the clients here read as fast as the topic runs.
    with another_daphne(tmp_path_factory.mktemp("blob-cloud") / "daphne.log") as (server, _):
        yield server


def ros1_string(payload: bytes) -> str:
    (length,) = struct.unpack_from("<I", payload)
    return payload[4 : 4 + length].decode()


@pytest.mark.ros
@pytest.mark.django_db(transaction=True)
@pytest.mark.timeout(120)
def test_five_clients_of_a_large_topic_get_it_whole_while_the_link_carries_one_copy(cloud, robot, ros) -> None:
    _, nodes = ros
    talker = nodes.run("big", "talker", "--topic", "/big", "--rate", "5", "--size", str(SIZE), "--tag", "big")
    before = counters(cloud)
    headers = {"Authorization": f"Token {robot.api_token}"}
    door = url(cloud, robot.id, "foxglove")
    foxes = [raw(door, additional_headers=headers, subprotocols=["foxglove.sdk.v1"]) for _ in range(3)]
    readers = [token_client(cloud, robot), token_client(cloud, robot)]
    heard: list[list[dict[str, Any]]] = [[], []]
    try:
        channel = None
        deadline = time.monotonic() + 20
        while channel is None and time.monotonic() < deadline:
            message = json.loads(foxes[0].recv(timeout=10))
            if message.get("op") == "advertise":
                channel = next((c["id"] for c in message["channels"] if c["topic"] == "/big"), None)
        assert channel is not None, "the Foxglove door never advertised /big"
        for fox, ident in zip(foxes, (1, 7, 42), strict=True):
            fox.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": ident, "channelId": channel}]}))
        for reader, into in zip(readers, heard, strict=True):
            roslibpy.Topic(reader, "/big", "std_msgs/String").subscribe(into.append)

        got: list[list[str]] = [[], [], []]
        deadline = time.monotonic() + 30
        while min(len(g) for g in got) < 8 and time.monotonic() < deadline:
            for fox, ident, into in zip(foxes, (1, 7, 42), got, strict=True):
                try:
                    frame = fox.recv(timeout=0.05)
                except TimeoutError:
                    continue
                if isinstance(frame, bytes) and frame[:1] == b"\x01":
                    _, subscription, _ = struct.unpack_from("<BIQ", frame)
                    assert subscription == ident  # each client's own head in front of the shared bytes
                    into.append(ros1_string(frame[13:]))
        wait_until(lambda: min(len(h) for h in heard) >= 8, timeout=30, what="the roslibpy clients' messages")
    finally:
        for fox in foxes:
            fox.close()
        for reader in readers:
            reader.close()
        talker.kill()
    texts = [text for one in got for text in one] + [m["data"] for one in heard for m in one]
    assert all(text.startswith("big ") and len(text) > SIZE for text in texts), "a message arrived cut or mixed"
    assert min(len(g) for g in got) >= 8, [len(g) for g in got]

    after = counters(cloud)
    shared = after["bridgeos_bridge_blob_bytes_total"] - before["bridgeos_bridge_blob_bytes_total"]
    delivered = after["bridgeos_bridge_bytes_total"] - before["bridgeos_bridge_bytes_total"]
    # Five clients, two encodings (Foxglove's raw bytes, rosbridge's JSON): about two copies cross
    # the link for five delivered; per-client copies would make it one for one.
    assert delivered > 5 * 8 * SIZE, delivered
    assert shared < 0.55 * delivered, (shared, delivered)
    assert robot.controller.bridges.blobs_sent > 0


@pytest.mark.ros
@pytest.mark.django_db(transaction=True)
@pytest.mark.timeout(120)
def test_a_client_on_another_cloud_process_gets_a_shared_frame_through_the_channel_layer(
    cloud, robot, ros, tmp_path
) -> None:
    _, nodes = ros
    talker = nodes.run("big", "talker", "--topic", "/big", "--rate", "5", "--size", str(SIZE), "--tag", "big")
    headers = {"Authorization": f"Token {robot.api_token}"}
    try:
        with (
            another_daphne(tmp_path / "second.log") as (second, _),
            raw(f"{second.ws_url}/ws/rosbridge/{robot.id}/", additional_headers=headers) as far,
            raw(url(cloud, robot.id), additional_headers=headers) as near,
        ):
            for websocket in (far, near):
                websocket.send(json.dumps({"op": "subscribe", "topic": "/big"}))
            for websocket in (far, near):
                deadline = time.monotonic() + 20
                while True:
                    message = json.loads(websocket.recv(timeout=max(0.1, deadline - time.monotonic())))
                    if message.get("op") == "publish":
                        break
                assert message["msg"]["data"].startswith("big ") and len(message["msg"]["data"]) > SIZE
    finally:
        talker.kill()
    assert robot.controller.bridges.blobs_sent > 0
