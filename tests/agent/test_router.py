"""The Skill Router against a private rosmaster, real rospy nodes, rostopic and real HTTP servers."""

from __future__ import annotations

import asyncio
import json
import logging
import subprocess
import xmlrpc.client
from collections.abc import AsyncIterator, Callable
from pathlib import Path

import aiohttp
import pytest
from aiohttp import web

from bridgeos_agent.rosnode import read_header
from bridgeos_agent.router import RouterSettings, SkillRouter, router_settings_from_env
from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_agent.tcpros import TOPIC_STATISTICS_MD5, TopicStatistics, encode_header
from tests.agent.roshelpers import HOST_PYTHON
from tests.conftest import eventually, free_port

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

SKILL = "relay"


def ns(component: str, location: str) -> str:
    return f"/bridgeos/{SKILL}/{component}/{location}"


def skill(router: dict, *, http_ports: dict[str, list[int]] | None = None) -> dict:
    """Return a Skill whose components are placeholders: the tests run their instances themselves."""
    components = {}
    for name in ("talker", "listener", "server", "web"):
        ports = (http_ports or {}).get(name, [])
        spec = {"command": ["true"], "ports": ports}
        components[name] = {
            "name": name.title(),
            "location": "either",
            "ros": name != "web",
            "robot": spec,
            "cloud": spec,
        }
    return {"skill": "Relay", "skill_id": SKILL, "components": components, "router": router}


CHATTER = {"name": "chatter", "type": "std_msgs/String", "publisher": "talker", "subscribers": ["listener"]}


@pytest.fixture
async def make_router(rosmaster: str, tmp_path: Path) -> AsyncIterator[Callable[..., object]]:
    """Build and start routers that are closed when the test ends."""
    routers: list[SkillRouter] = []

    async def make(config: dict, *, master: str | None = rosmaster, **active: str) -> SkillRouter:
        settings = RouterSettings(http_host="127.0.0.1", statistics_period=0.5)
        router = SkillRouter(parse_skill_config(config), ros_master=master, settings=settings, state_dir=tmp_path)
        for component, location in active.items():
            router.set_active(component, location)
        routers.append(router)
        await router.start()
        return router

    yield make
    for router in routers:
        await router.close()


def system_state(master: str, node: str) -> tuple[set[str], set[str], set[str]]:
    """Return the topics a node publishes and subscribes, and the services it serves, as the master knows."""
    code, _, (pubs, subs, services) = xmlrpc.client.ServerProxy(master).getSystemState("/test")
    assert code == 1
    return tuple({name for name, nodes in kind if node in nodes} for kind in (pubs, subs, services))


# ---------------------------------------------------------------------- topics


async def test_a_robot_talker_reaches_canonical_listeners_and_an_outside_publisher_reaches_the_component(
    nodes, make_router
):
    router = await make_router(skill({"topics": [CHATTER]}), talker="robot", listener="robot")
    nodes.run("component", "listener", namespace=ns("listener", "robot"))
    nodes.run("canonical", "listener", "--topic", "/chatter")
    nodes.run("talker-robot", "talker", "--tag", "robot", "--rate", "50", "--wait", namespace=ns("talker", "robot"))
    # The idle cloud copy publishes too, but its traffic goes nowhere.
    nodes.run("talker-cloud", "talker", "--tag", "cloud", "--rate", "50", "--wait", namespace=ns("talker", "cloud"))
    assert await router.wait_ready("talker", "robot", 45)
    assert await router.wait_ready("talker", "cloud", 45)
    assert await router.wait_ready("listener", "robot", 45)
    for key in ("component", "canonical"):
        await eventually(
            lambda key=key: len(nodes.messages(key)) >= 20, timeout=45, what=f"{key} listener hears the talker"
        )
    for key in ("component", "canonical"):
        assert {tag for tag, _ in nodes.messages(key)} == {"robot"}
    # "And vice versa": rostopic publishing on the canonical name reaches the component's instance.
    nodes.command(
        "rostopic", "/usr/bin/rostopic", "pub", "-r", "20", "/chatter", "std_msgs/String", "data: 'outside 1 0'"
    )
    await eventually(
        lambda: ("outside", 1) in nodes.messages("component"), timeout=45, what="rostopic's message at the component"
    )
    # The router never sends its own canonical publication back to itself.
    canonical_tags = {tag for tag, _ in nodes.messages("canonical")}
    assert canonical_tags <= {"robot", "outside"}
    assert router.statistics()["/chatter"]["subscribers"]["listener"]["messages"] >= 20


def _contiguous(seqs: list[int]) -> bool:
    return seqs == list(range(seqs[0], seqs[0] + len(seqs))) if seqs else True


async def test_switching_the_talker_under_a_1khz_stream_loses_and_duplicates_nothing(nodes, make_router):
    router = await make_router(skill({"topics": [CHATTER]}), talker="robot", listener="robot")
    nodes.run("canonical", "listener", "--topic", "/chatter")
    nodes.run("component", "listener", namespace=ns("listener", "robot"))
    assert await router.wait_ready("listener", "robot", 45)
    await eventually(
        lambda: router.node.publications["/chatter"].connections, timeout=45, what="the canonical listener"
    )
    nodes.run("robot", "talker", "--tag", "robot", "--rate", "1000", "--wait", namespace=ns("talker", "robot"))
    await eventually(lambda: len(nodes.messages("canonical")) >= 300, timeout=45, what="the robot stream")
    nodes.run("cloud", "talker", "--tag", "cloud", "--rate", "1000", "--wait", namespace=ns("talker", "cloud"))
    assert await router.wait_ready("talker", "cloud", 45)
    await router.switch("talker", "cloud")
    assert router.active("talker") == "cloud"
    switched_at = len(nodes.messages("canonical"))
    await eventually(lambda: len(nodes.messages("canonical")) >= switched_at + 500, timeout=45, what="the cloud stream")
    for key in ("canonical", "component"):
        heard = nodes.messages(key)
        tags = [tag for tag, _ in heard]
        cut = tags.index("cloud")
        assert set(tags[:cut]) == {"robot"} and set(tags[cut:]) == {"cloud"}, f"{key}: the streams interleave"
        robot = [seq for _, seq in heard[:cut]]
        cloud = [seq for _, seq in heard[cut:]]
        assert robot[0] == 1 and _contiguous(robot), f"{key}: the robot stream lost or repeated messages"
        assert _contiguous(cloud), f"{key}: the cloud stream lost or repeated messages after the switch"
    stats = router.statistics()["/chatter"]
    assert stats["dropped"] == 0


async def test_pointclouds_of_the_thesis_size_are_relayed_whole(nodes, make_router):
    # Thesis §5.3.1: RGB-D pointclouds of 30-40 MB. Each one must arrive whole, in order, once.
    router = await make_router(skill({"topics": [CHATTER]}), talker="robot", listener="robot")
    nodes.run("canonical", "listener", "--topic", "/chatter")
    await eventually(
        lambda: router.node.publications["/chatter"].connections, timeout=45, what="the canonical listener"
    )
    nodes.run(
        "robot",
        "talker",
        "--tag",
        "robot",
        "--rate",
        "2",
        "--count",
        "4",
        "--size",
        str(35 << 20),
        "--wait",
        namespace=ns("talker", "robot"),
    )
    await eventually(lambda: len(nodes.messages("canonical")) >= 4, timeout=90, what="four 35 MB messages")
    assert nodes.messages("canonical") == [("robot", seq) for seq in range(1, 5)]
    stats = router.statistics()["/chatter"]
    assert stats["dropped"] == 0 and stats["bytes"] >= 4 * (35 << 20)


async def test_switching_the_listener_delivers_every_message_exactly_once(nodes, make_router):
    router = await make_router(skill({"topics": [CHATTER]}), talker="robot", listener="robot")
    nodes.run("listener-robot", "listener", namespace=ns("listener", "robot"))
    nodes.run("listener-cloud", "listener", namespace=ns("listener", "cloud"))
    assert await router.wait_ready("listener", "robot", 45)
    assert await router.wait_ready("listener", "cloud", 45)
    nodes.run(
        "talker", "talker", "--tag", "t", "--rate", "1000", "--count", "3000", "--wait", namespace=ns("talker", "robot")
    )
    await eventually(lambda: len(nodes.messages("listener-robot")) >= 500, timeout=45, what="the robot listener hears")
    await router.switch("listener", "cloud")
    await eventually(
        lambda: any(line.startswith("sent") for line in nodes.lines("talker")), timeout=45, what="the talker ends"
    )
    await eventually(
        lambda: len(nodes.messages("listener-robot")) + len(nodes.messages("listener-cloud")) >= 3000,
        timeout=45,
        what="every message delivered",
    )
    robot = [seq for _, seq in nodes.messages("listener-robot")]
    cloud = [seq for _, seq in nodes.messages("listener-cloud")]
    assert cloud, "the cloud listener heard nothing after the switch"
    assert robot + cloud == list(range(1, 3001))


async def test_topics_are_added_and_removed_at_runtime(rosmaster, make_router):
    config = skill({"topics": [CHATTER]})
    router = await make_router(config, talker="robot", listener="robot")
    pubs, subs, _ = system_state(rosmaster, router.node.name)
    assert "/chatter" in pubs and f"{ns('talker', 'robot')}/chatter" in subs
    extra = {"name": "/scan", "type": "std_msgs/String", "publisher": "listener", "subscribers": ["talker"]}
    await router.apply(parse_skill_config(skill({"topics": [extra]})))
    pubs, subs, _ = system_state(rosmaster, router.node.name)
    assert "/scan" in pubs and f"{ns('listener', 'cloud')}/scan" in subs and f"{ns('talker', 'robot')}/scan" in pubs
    assert "/chatter" not in pubs and f"{ns('talker', 'robot')}/chatter" not in subs
    assert set(router.statistics()) == {"/scan"}


async def test_a_stalled_subscriber_of_a_big_topic_delays_no_other_topic(nodes, make_router):
    big = {"name": "big", "type": "std_msgs/String", "publisher": "server", "subscribers": []}
    router = await make_router(skill({"topics": [CHATTER, big]}), talker="robot", listener="robot", server="robot")
    # A subscriber of /big that connects and then never reads (fault injection: a stalled peer).
    reader, writer = await asyncio.open_connection("127.0.0.1", router.node.tcpros_port)
    fields = {"callerid": "/stalled", "topic": "/big", "md5sum": "*", "type": "std_msgs/String"}
    writer.write(encode_header(fields))
    header = await asyncio.wait_for(read_header(reader), 30)
    assert "error" not in header
    try:
        nodes.run("listener", "listener", namespace=ns("listener", "robot"))
        assert await router.wait_ready("listener", "robot", 45)
        nodes.run(
            "big",
            "talker",
            "--topic",
            "big",
            "--tag",
            "big",
            "--rate",
            "1000",
            "--size",
            "20000",
            "--wait",
            namespace=ns("server", "robot"),
        )
        await eventually(
            lambda: router.statistics()["/big"]["dropped"] > 0, timeout=45, what="the stalled subscriber's drops"
        )
        nodes.run(
            "small",
            "talker",
            "--tag",
            "s",
            "--rate",
            "200",
            "--count",
            "400",
            "--wait",
            namespace=ns("talker", "robot"),
        )
        await eventually(lambda: len(nodes.messages("listener")) >= 400, timeout=45, what="every small message")
        assert nodes.messages("listener") == [("s", seq) for seq in range(1, 401)]
        stats = router.statistics()
        assert stats["/chatter"]["dropped"] == 0 and stats["/big"]["dropped"] > 0
        assert router.traffic("server").dropped > 0 and router.traffic("talker").dropped == 0
    finally:
        writer.close()


# ---------------------------------------------------------------------- statistics


def test_topic_statistics_serialise_as_debians_rosgraph_msgs_reads_them():
    stats = TopicStatistics(
        topic="/chatter",
        node_pub="/talker",
        node_sub="/bridgeos/relay/router",
        window_start=1700000000.25,
        window_stop=1700000001.5,
        delivered_msgs=1000,
        dropped_msgs=3,
        traffic=123456,
        period_mean=0.001,
        period_stddev=0.0002,
        period_max=0.004,
        stamp_age_mean=0.0005,
        stamp_age_stddev=0.0001,
        stamp_age_max=0.002,
    )
    code = (
        "import sys, json, rosgraph_msgs.msg as m\n"
        "s = m.TopicStatistics().deserialize(bytes.fromhex(sys.argv[1]))\n"
        "d = lambda v: v.to_sec()\n"
        "print(json.dumps([m.TopicStatistics._md5sum, s.topic, s.node_pub, s.node_sub, d(s.window_start),"
        " d(s.window_stop), s.delivered_msgs, s.dropped_msgs, s.traffic, d(s.period_mean), d(s.period_stddev),"
        " d(s.period_max), d(s.stamp_age_mean), d(s.stamp_age_stddev), d(s.stamp_age_max)]))\n"
        "import io; b = io.BytesIO(); s.serialize(b); print(b.getvalue().hex())"
    )
    data = stats.serialize()
    out = subprocess.run([HOST_PYTHON, "-c", code, data.hex()], capture_output=True, text=True, timeout=60, check=True)
    fields, reserialized = out.stdout.splitlines()
    assert reserialized == data.hex()
    md5, *values = json.loads(fields)
    assert md5 == TOPIC_STATISTICS_MD5
    assert values == [
        "/chatter",
        "/talker",
        "/bridgeos/relay/router",
        1700000000.25,
        1700000001.5,
        1000,
        3,
        123456,
        0.001,
        0.0002,
        0.004,
        0.0005,
        0.0001,
        0.002,
    ]


STATISTICS_LISTENER = """
import json, rospy, sys
from rosgraph_msgs.msg import TopicStatistics
rospy.init_node("stats", anonymous=True, disable_signals=True)
def got(m):
    print(json.dumps([m.topic, m.delivered_msgs, m.dropped_msgs, m.traffic]), flush=True)
rospy.Subscriber("/statistics", TopicStatistics, got, queue_size=None)
print("ready", flush=True)
rospy.spin()
"""


async def test_statistics_match_what_was_sent(nodes, make_router, tmp_path):
    router = await make_router(skill({"topics": [CHATTER]}), talker="robot", listener="cloud")
    script = tmp_path / "stats.py"
    script.write_text(STATISTICS_LISTENER)
    nodes.command("stats", str(script))
    await eventually(
        lambda: router.node.publications["/statistics"].connections, timeout=45, what="a /statistics listener"
    )
    nodes.run("listener", "listener", namespace=ns("listener", "cloud"))
    assert await router.wait_ready("listener", "cloud", 45)
    router.traffic("talker"), router.traffic("listener")  # start both windows now
    count, size = 200, 100
    nodes.run(
        "talker",
        "talker",
        "--tag",
        "t",
        "--rate",
        "200",
        "--count",
        str(count),
        "--size",
        str(size),
        "--wait",
        namespace=ns("talker", "robot"),
    )
    await eventually(lambda: len(nodes.messages("listener")) == count, timeout=45, what="every message at the listener")
    # Each std_msgs/String is a 4-byte length and "t <seq> <time> <padding>".
    expected_bytes = sum(4 + len(f"t {seq} 1700000000.000000 ") + size for seq in range(1, count + 1))
    stats = router.statistics()["/chatter"]
    assert stats["messages"] == count and stats["dropped"] == 0 and stats["delivery_ratio"] == 1.0
    assert "rate_hz" in stats and stats["latency_ms"] is None  # std_msgs/String has no header.stamp
    assert stats["subscribers"]["listener"] == {"messages": count, "dropped": 0, "bytes": expected_bytes}
    talker, listener = router.traffic("talker"), router.traffic("listener")
    assert (talker.messages, talker.dropped, talker.bytes_cloud, talker.bytes_robot) == (count, 0, expected_bytes, 0)
    assert (listener.messages, listener.bytes_robot, listener.bytes_cloud) == (count, expected_bytes, 0)
    assert router.traffic("talker").messages == 0  # counts are since the previous call

    def published() -> list[list]:
        rows = [json.loads(line) for line in nodes.lines("stats") if line.startswith("[")]
        return [row for row in rows if row[0] == "/chatter"]

    await eventually(lambda: sum(row[1] for row in published()) == count, timeout=45, what="/statistics adds up")
    rows = published()
    assert sum(row[3] for row in rows) == expected_bytes and sum(row[2] for row in rows) == 0


# ---------------------------------------------------------------------- services


CALL = """
import rospy, sys
from std_srvs.srv import Trigger
rospy.wait_for_service("/trigger", timeout=30)
proxy = rospy.ServiceProxy("/trigger", Trigger, persistent=len(sys.argv) > 1)
print(" ".join(proxy().message for _ in range(3)))
"""


async def test_a_service_call_reaches_the_active_instance(nodes, make_router):
    route = {"name": "trigger", "type": "std_srvs/Trigger", "server": "server"}
    router = await make_router(skill({"services": [route]}), server="robot")
    nodes.run("robot", "server", "--tag", "robot", namespace=ns("server", "robot"))
    nodes.run("cloud", "server", "--tag", "cloud", namespace=ns("server", "cloud"))
    assert await router.wait_ready("server", "robot", 45)
    call = await asyncio.to_thread(nodes.tool, "-c", CALL)
    assert call.stdout.split() == ["robot"] * 3, call.stderr
    assert await router.wait_ready("server", "cloud", 45)
    await router.switch("server", "cloud")
    call = await asyncio.to_thread(nodes.tool, "-c", CALL, "persistent")
    assert call.stdout.split() == ["cloud"] * 3, call.stderr
    rosservice = await asyncio.to_thread(nodes.tool, "/usr/bin/rosservice", "call", "/trigger")
    assert "cloud" in rosservice.stdout, rosservice.stderr
    assert router.statistics()["/trigger"]["calls"] == 7
    assert router.traffic("server").messages == 7


# ---------------------------------------------------------------------- HTTP


async def _instance(tag: str, slow: asyncio.Event | None = None) -> tuple[web.AppRunner, int]:
    """Serve one web component instance that says which instance answered."""

    async def answer(request: web.Request) -> web.Response:
        if request.path.endswith("/slow") and slow is not None:
            await slow.wait()
        body = await request.read()
        return web.json_response({"instance": tag, "path": request.path_qs, "body": body.decode()})

    app = web.Application()
    app.router.add_route("*", "/{tail:.*}", answer)
    runner = web.AppRunner(app)
    await runner.setup()
    port = free_port()
    await web.TCPSite(runner, "127.0.0.1", port).start()
    return runner, port


async def test_http_is_proxied_to_the_active_instance_and_follows_a_switch_without_ros(make_router, caplog):
    slow = asyncio.Event()
    robot, robot_port = await _instance("robot", slow)
    cloud, cloud_port = await _instance("cloud")
    try:
        route = {"component": "web", "prefix": "/api", "methods": ["GET", "POST"]}
        topic = {"name": "chatter", "type": "std_msgs/String", "publisher": "talker", "subscribers": []}
        config = skill({"http": [route], "topics": [topic]}, http_ports={"web": [robot_port]})
        with caplog.at_level(logging.INFO, logger="bridgeos_agent.router"):
            router = await make_router(config, master=None, web="robot")
        off = [r.getMessage() for r in caplog.records if "ROS routing is off" in r.getMessage()]
        assert len(off) == 1 and "HTTP routing still works" in off[0]
        assert not router.ros_on and router.url
        # The cloud instance listens on its container port, published on another port of the host.
        router.set_container("web", "cloud", {"address": "127.0.0.1", "ports": {str(robot_port): cloud_port}})
        async with aiohttp.ClientSession(base_url=router.url) as http:
            async with http.get("/api/items?q=1") as response:
                assert response.status == 200
                assert await response.json() == {"instance": "robot", "path": "/api/items?q=1", "body": ""}
            async with http.post("/api/items", data=b"hello") as response:
                assert (await response.json())["body"] == "hello"
            async with http.delete("/api/items") as response:
                assert response.status == 405 and response.headers["Allow"] == "GET, POST"
            async with http.get("/elsewhere") as response:
                assert response.status == 404
            assert await router.wait_ready("web", "cloud", 30)
            # A request already at the old instance finishes there; the switch waits for it.
            pending = asyncio.create_task(http.get("/api/slow"))
            await eventually(
                lambda: router._inflight.get(("web", "robot")), timeout=45, what="the slow request in flight"
            )
            switching = asyncio.create_task(router.switch("web", "cloud"))
            async with http.get("/api/items") as response:
                assert (await response.json())["instance"] == "cloud"
            assert not switching.done()
            slow.set()
            async with await pending as response:
                assert (await response.json())["instance"] == "robot"
            await asyncio.wait_for(switching, 10)
        traffic = router.traffic("web")
        assert traffic.messages == 4 and traffic.dropped == 0
    finally:
        await robot.cleanup()
        await cloud.cleanup()


async def test_an_instance_without_an_address_is_not_ready_and_gets_a_clear_503(make_router):
    route = {"component": "web", "prefix": "/", "methods": ["GET"], "port": 8080}
    router = await make_router(skill({"http": [route]}), master=None, web="cloud")
    assert not await router.wait_ready("web", "cloud", 0.5)
    async with aiohttp.ClientSession(base_url=router.url) as http, http.get("/anything") as response:
        assert response.status == 503
        assert "no known address on the cloud" in (await response.json())["error"]


def test_router_settings_refuse_bad_values_with_a_clear_error():
    with pytest.raises(ValueError, match="BRIDGEOS_ROUTER_READY_TIMEOUT"):
        router_settings_from_env({"BRIDGEOS_ROUTER_READY_TIMEOUT": "soon"})
    with pytest.raises(ValueError, match="ready_timeout"):
        router_settings_from_env({"BRIDGEOS_ROUTER_READY_TIMEOUT": "-1"})
    with pytest.raises(ValueError, match="http_host"):
        router_settings_from_env({"BRIDGEOS_ROUTER_HTTP_HOST": "a b"})
    settings = router_settings_from_env({"ROS_IP": "10.0.0.5", "BRIDGEOS_ROUTER_HTTP_HOST": "0.0.0.0"})
    assert (settings.ros_host, settings.http_advertise) == ("10.0.0.5", "127.0.0.1")


async def test_a_skill_without_routes_costs_nothing(make_router):
    router = await make_router(skill({}), talker="robot")
    assert router.node is None and router.url is None
    assert await router.wait_ready("talker", "cloud", 0.1)
    with pytest.raises(ValueError, match="no component"):
        router.set_active("nobody", "robot")
    with pytest.raises(KeyError, match="routes nothing"):
        router.traffic("talker")  # the manager reads this as "no measurement", not as zero traffic
