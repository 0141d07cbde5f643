"""Cloud-side routing: the robot's router, a cloud relay process, rospy nodes and a private rosmaster.

The cloud relay runs as its own process (``python -m bridgeos_agent.router.cloudrelay``), as the
cloud's worker runs it. Bytes are read from the rospy nodes' own bus statistics (getBusStats), so
what crossed which connection is measured by the peers, not by the routers.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import os
import subprocess
import sys
import xmlrpc.client
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path

import pytest

import bridgeos_agent
from bridgeos_agent.router import RouterSettings, SkillRouter
from bridgeos_agent.router.cloudlink import CloudLink, link_from_env
from bridgeos_agent.router.handover import FrameLog, fingerprint
from bridgeos_agent.skillconfig import parse_skill_config
from tests.conftest import eventually

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

SKILL = "chat"
TOKEN = "relay-test-token"
CHATTER = {"name": "chatter", "type": "std_msgs/String", "publisher": "talker", "subscribers": ["listener"]}
CONFIG = {
    "skill": "Chat",
    "skill_id": SKILL,
    "components": {
        name: {
            "name": name.title(),
            "location": "either",
            "robot": {"command": ["true"]},
            "cloud": {"command": ["true"]},
        }
        for name in ("talker", "listener")
    },
    "router": {"topics": [CHATTER]},
}


def ns(component: str, location: str) -> str:
    return f"/bridgeos/{SKILL}/{component}/{location}"


@pytest.fixture
def cloud_relay(rosmaster: str, tmp_path: Path) -> Iterator[dict]:
    """Run the cloud relay process the cloud's worker would run; yield what it printed."""
    config = tmp_path / "skill.json"
    config.write_text(json.dumps(CONFIG))
    env = {**os.environ, "PYTHONPATH": str(Path(bridgeos_agent.__file__).parents[1]), "PYTHONWARNINGS": "ignore"}
    argv = ["--config", str(config), "--master", rosmaster, "--robot", "r1", "--token", TOKEN]
    process = subprocess.Popen(
        [sys.executable, "-m", "bridgeos_agent.router.cloudrelay", *argv],
        env=env,
        stdout=subprocess.PIPE,
        stderr=(tmp_path / "relay.log").open("wb"),
        text=True,
        start_new_session=True,
    )
    try:
        line = process.stdout.readline() if process.stdout else ""
        assert line.startswith("{"), (tmp_path / "relay.log").read_text()
        yield json.loads(line)
    finally:
        process.kill()
        process.wait(10)


@pytest.fixture
async def make_router(rosmaster: str, tmp_path: Path) -> AsyncIterator[Callable[..., object]]:
    routers: list[SkillRouter] = []

    async def make(link: CloudLink | None, **active: str) -> SkillRouter:
        settings = RouterSettings(http_host="127.0.0.1", statistics_period=0.5, drain_timeout=5)
        router = SkillRouter(parse_skill_config(CONFIG), ros_master=rosmaster, settings=settings, robot="r1")
        router.cloud_link = link
        for component, location in active.items():
            router.set_active(component, location)
        routers.append(router)
        await router.start()
        return router

    yield make
    for router in routers:
        await router.close()


def bytes_by_peer(master: str, topic: str) -> dict[str, int]:
    """Return, as the rospy subscriber of ``topic`` counts them, the bytes it received from each publisher node."""
    proxy = xmlrpc.client.ServerProxy(master)
    _, _, (_, subscribers, _) = proxy.getSystemState("/test")
    (node,) = next(names for name, names in subscribers if name == topic)
    uri = proxy.lookupNode("/test", node)[2]
    _, _, info = xmlrpc.client.ServerProxy(uri).getBusInfo("/test")
    _, _, (_, subscribe_stats, _) = xmlrpc.client.ServerProxy(uri).getBusStats("/test")
    received = {conn_id: size for name, conns in subscribe_stats if name == topic for conn_id, size, *_ in conns}
    publishers = {}
    for uri_, node_ in _publisher_nodes(proxy, topic):
        publishers[uri_] = node_
    found: dict[str, int] = {}
    for conn_id, endpoint, *_ in info:
        peer = publishers.get(endpoint.rstrip("/"), endpoint)
        found[peer] = found.get(peer, 0) + received.get(conn_id, 0)
    return found


def _publisher_nodes(proxy: xmlrpc.client.ServerProxy, topic: str) -> list[tuple[str, str]]:
    _, _, (publishers, _, _) = proxy.getSystemState("/test")
    names = next((names for name, names in publishers if name == topic), [])
    return [(proxy.lookupNode("/test", name)[2].rstrip("/"), name) for name in names]


def subscribers_of(master: str, topic: str) -> set[str]:
    _, _, (_, subscribers, _) = xmlrpc.client.ServerProxy(master).getSystemState("/test")
    return set(next((names for name, names in subscribers if name == topic), []))


# ---------------------------------------------------------------------- the cut point


def test_a_frame_log_finds_the_frame_after_a_cut_point_and_says_when_it_has_not_seen_it():
    frames = [len(body).to_bytes(4, "little") + body for body in (b"a 1", b"a 2", b"a 3", b"a 4", b"a 5", b"a 6")]
    mine, theirs = FrameLog(), FrameLog()
    mine.add(b"".join(frames[:4]), 4)
    anchor = mine.anchor()
    assert anchor == [fingerprint(f) for f in frames[:4]]
    theirs.add(b"".join(frames[1:3]), 2)
    assert theirs.after(anchor) is None  # not there yet: the taker waits for it
    theirs.add(b"".join(frames[3:]), 3)
    assert theirs.after(anchor) == frames[4:]
    assert FrameLog().anchor() is None


# ---------------------------------------------------------------------- real nodes


async def test_a_cloud_to_cloud_link_does_not_cross_the_robots_router(nodes, make_router, cloud_relay, rosmaster):
    link = CloudLink(cloud_relay["url"], TOKEN, poll=0.3)
    router = await make_router(link, talker="cloud", listener="cloud")
    assert link.up
    nodes.run("listener", "listener", namespace=ns("listener", "cloud"))
    assert await router.wait_ready("listener", "cloud", 45)
    count = 400
    nodes.run(
        "talker", "talker", "--tag", "c", "--rate", "200", "--count", str(count), "--size", "1000", "--wait",
        namespace=ns("talker", "cloud"),
    )  # fmt: skip
    await eventually(
        lambda: len(nodes.messages("listener")) >= count, timeout=45, what="every message at the cloud listener"
    )
    assert nodes.messages("listener") == [("c", seq) for seq in range(1, count + 1)]
    # The talker's stream reaches the relay only: the robot's router is not even subscribed to it.
    source = f"{ns('talker', 'cloud')}/chatter"
    assert subscribers_of(rosmaster, source) == {cloud_relay["node"]}
    # The listener counts what each publisher sent it: all from the relay, nothing from the robot's router.
    received = bytes_by_peer(rosmaster, f"{ns('listener', 'cloud')}/chatter")
    assert received.get(router.node.name, 0) < 512  # its connection header: not one message
    assert received[cloud_relay["node"]] >= count * 1000
    # The relay's counts reach the Skill Manager through the robot's router.
    await eventually(
        lambda: link.counts.get("/chatter", {}).get("messages") == count, timeout=45, what="the relay's counts"
    )
    stats = router.statistics()["/chatter"]
    assert stats["messages"] == count and stats["subscribers"]["listener"]["messages"] == count
    assert stats["dropped"] == 0
    traffic = router.traffic("listener")
    assert traffic.messages == count and traffic.bytes_cloud >= count * 1000 and traffic.bytes_robot == 0


async def test_switching_the_subscriber_robot_cloud_robot_under_a_1khz_stream_loses_and_repeats_nothing(
    nodes, make_router, cloud_relay, rosmaster
):
    link = CloudLink(cloud_relay["url"], TOKEN, poll=0.3)
    router = await make_router(link, talker="cloud", listener="robot")
    nodes.run("robot", "listener", namespace=ns("listener", "robot"))
    nodes.run("cloud", "listener", namespace=ns("listener", "cloud"))
    total = 6000
    nodes.run(
        "talker", "talker", "--tag", "t", "--rate", "1000", "--count", str(total), "--wait",
        namespace=ns("talker", "cloud"),
    )  # fmt: skip
    assert await router.wait_ready("listener", "robot", 45)
    await eventually(
        lambda: len(nodes.messages("robot")) >= 800, timeout=45, what="the robot listener hears the cloud talker"
    )
    assert await router.wait_ready("listener", "cloud", 45)
    await router.switch("listener", "cloud")
    await eventually(lambda: len(nodes.messages("cloud")) >= 1000, timeout=45, what="the cloud listener via the relay")
    assert subscribers_of(rosmaster, f"{ns('talker', 'cloud')}/chatter") == {cloud_relay["node"]}
    assert await router.wait_ready("listener", "robot", 45)
    await router.switch("listener", "robot")
    await eventually(lambda: any(line.startswith("sent") for line in nodes.lines("talker")), 60, "the talker ends")
    await eventually(lambda: ("t", total) in nodes.messages("robot")[-5:], 30, "the last message at the robot")
    await asyncio.sleep(0.3)  # anything repeated would arrive by now
    robot = [seq for _, seq in nodes.messages("robot")]
    cloud = [seq for _, seq in nodes.messages("cloud")]
    assert cloud and robot[-1] == total, "both instances took part"
    # (The stream may begin before the robot's listener is connected: its first message is the start.)
    first = robot[0]
    assert cloud == list(range(cloud[0], cloud[0] + len(cloud))), "the cloud listener's share has a gap"
    assert robot == [s for s in range(first, total + 1) if not cloud[0] <= s <= cloud[-1]], "the robot's share"
    await eventually(
        lambda: link.counts.get("/chatter", {}).get("deliveries", {}).get("listener", [0])[0] == len(cloud), timeout=45
    )
    stats = router.statistics()["/chatter"]
    # The robot's own count plus the relay's (the robot's counts what it sent before its listener connected).
    own = router._topics["/chatter"].deliveries["listener"].messages
    assert own >= len(robot) and stats["subscribers"]["listener"]["messages"] == own + len(cloud)
    assert stats["dropped"] == 0


async def test_moving_the_publisher_into_the_cloud_hands_the_link_to_the_relay_without_interleaving(
    nodes, make_router, cloud_relay, rosmaster
):
    # The listener already runs in the cloud; the talker moves robot -> cloud -> robot under a 1 kHz stream.
    link = CloudLink(cloud_relay["url"], TOKEN, poll=0.3)
    router = await make_router(link, talker="robot", listener="cloud")
    nodes.run("listener", "listener", namespace=ns("listener", "cloud"))
    assert await router.wait_ready("listener", "cloud", 45)
    nodes.run("robot", "talker", "--tag", "robot", "--rate", "1000", "--wait", namespace=ns("talker", "robot"))
    await eventually(
        lambda: len(nodes.messages("listener")) >= 500, timeout=45, what="the robot talker at the cloud listener"
    )
    nodes.run("cloud", "talker", "--tag", "cloud", "--rate", "1000", "--wait", namespace=ns("talker", "cloud"))
    assert await router.wait_ready("talker", "cloud", 45)
    await router.switch("talker", "cloud")
    await eventually(
        lambda: subscribers_of(rosmaster, f"{ns('talker', 'cloud')}/chatter") == {cloud_relay["node"]}, timeout=45
    )
    heard = len(nodes.messages("listener"))
    await eventually(
        lambda: len(nodes.messages("listener")) >= heard + 500, timeout=45, what="the cloud talker via the relay"
    )
    assert await router.wait_ready("talker", "robot", 45)
    await router.switch("talker", "robot")
    heard = len(nodes.messages("listener"))
    await eventually(lambda: len(nodes.messages("listener")) >= heard + 500, timeout=45, what="the robot talker again")
    tags = [tag for tag, _ in nodes.messages("listener")]
    runs = [tags[0]] + [b for a, b in itertools.pairwise(tags) if a != b]
    assert runs == ["robot", "cloud", "robot"], "the streams interleave at a switch"
    cut = tags.index("cloud")
    back = cut + tags[cut:].index("robot")
    heard_seqs = [seq for _, seq in nodes.messages("listener")]
    for part in (heard_seqs[:cut], heard_seqs[cut:back], heard_seqs[back:]):
        assert part == list(range(part[0], part[0] + len(part))), "a stream lost or repeated messages"


async def test_a_subscriber_stopped_in_the_cloud_and_started_on_the_robot_is_served_by_the_robot(
    nodes, make_router, cloud_relay, rosmaster
):
    link = CloudLink(cloud_relay["url"], TOKEN, poll=0.3)
    router = await make_router(link, talker="cloud", listener="cloud")
    nodes.run("talker", "talker", "--tag", "c", "--rate", "200", namespace=ns("talker", "cloud"))
    await eventually(lambda: link.owned == {("/chatter", "listener")}, timeout=45, what="the pair handed to the relay")
    router.set_active("listener", None)  # the component stops...
    await eventually(lambda: not link.owned, timeout=45, what="the pair taken back")
    nodes.run("robot", "listener", namespace=ns("listener", "robot"))
    assert await router.wait_ready("listener", "robot", 45)
    router.set_active("listener", "robot")  # ...and starts again on the robot
    await eventually(
        lambda: len(nodes.messages("robot")) >= 50, timeout=45, what="the robot's router serving the robot listener"
    )
    seqs = [seq for _, seq in nodes.messages("robot")]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))


async def test_without_a_reachable_relay_the_robots_router_relays_everything_and_says_so(nodes, make_router, caplog):
    link = CloudLink("http://127.0.0.1:9", TOKEN)  # nothing listens on the discard port
    with caplog.at_level(logging.WARNING, logger="bridgeos_agent.router"):
        router = await make_router(link, talker="cloud", listener="cloud")
    said = [r.getMessage() for r in caplog.records if "relays every link itself" in r.getMessage()]
    assert len(said) == 1 and "unreachable" in said[0]
    assert not link.up
    nodes.run("listener", "listener", namespace=ns("listener", "cloud"))
    assert await router.wait_ready("listener", "cloud", 45)
    nodes.run(
        "talker", "talker", "--tag", "c", "--rate", "200", "--count", "100", "--wait", namespace=ns("talker", "cloud")
    )
    await eventually(
        lambda: len(nodes.messages("listener")) >= 100, timeout=45, what="the listener through the robot's router"
    )
    assert nodes.messages("listener") == [("c", seq) for seq in range(1, 101)]
    assert router.statistics()["/chatter"]["subscribers"]["listener"]["messages"] == 100


async def test_the_relay_refuses_a_caller_without_its_token_and_bad_handovers(cloud_relay):
    import aiohttp

    async with aiohttp.ClientSession() as http:
        async with http.post(cloud_relay["url"] + "/take", json={"active": {}, "pairs": []}) as response:
            assert response.status == 401
        headers = {"Authorization": f"Bearer {TOKEN}"}
        bad = {"active": {"talker": "moon"}, "pairs": []}
        async with http.post(cloud_relay["url"] + "/take", json=bad, headers=headers) as response:
            assert response.status == 400 and "cannot run on the 'moon'" in (await response.json())["error"]
        robot_pair = {"active": {"talker": "cloud", "listener": "robot"}, "pairs": [["/chatter", "listener", None]]}
        async with http.post(cloud_relay["url"] + "/take", json=robot_pair, headers=headers) as response:
            assert response.status == 400 and "not cloud to cloud" in (await response.json())["error"]


def test_the_relay_setting_is_checked_and_names_the_skill():
    assert link_from_env("chat", {}) is None
    link = link_from_env(
        "chat", {"BRIDGEOS_CLOUD_RELAY_URL": "http://cloud:8000/{skill}/", "BRIDGEOS_CLOUD_RELAY_TOKEN": "t"}
    )
    assert link is not None and link.url == "http://cloud:8000/chat"
    with pytest.raises(ValueError, match="not an http"):
        link_from_env("chat", {"BRIDGEOS_CLOUD_RELAY_URL": "cloud:8000", "BRIDGEOS_CLOUD_RELAY_TOKEN": "t"})
    with pytest.raises(ValueError, match="TOKEN is needed"):
        link_from_env("chat", {"BRIDGEOS_CLOUD_RELAY_URL": "http://cloud:8000"})
