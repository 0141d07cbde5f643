"""Foxglove's parameters and time through the cloud: the real @foxglove/ws-protocol client → daphne → a real agent → ROS 1.

The cloud passes Foxglove frames through unread (JSON text and binary alike), so getParameters,
setParameters, parameter updates and the binary time frames cross it as any other; the cloud, the
robot and its private rosmaster are those of test_bridge_relay.
"""

from __future__ import annotations

import asyncio
import json
import xmlrpc.client
from collections.abc import Iterator
from typing import Any

import pytest

from tests.agent.foxgloveclient import FoxgloveClient, node_client_ready
from tests.agent.roshelpers import Nodes
from tests.cloud.test_bridge_relay import Bot, cloud, robot, ros, ticket
from tests.conftest import LoopThread, Server

pytestmark = [
    pytest.mark.ros,
    pytest.mark.django_db(transaction=True),
    pytest.mark.timeout(120),
    pytest.mark.skipif(not node_client_ready(), reason="node or tests/js/foxglove/node_modules is missing"),
]
__all__ = ["cloud", "robot", "ros"]  # test_bridge_relay's fixtures, this module's own instances


@pytest.fixture
def client(cloud: Server, robot: Bot) -> Iterator[FoxgloveClient]:
    client = FoxgloveClient(ticket(cloud, robot.id, robot.api_token)["foxglove_url"])
    try:
        yield client
    finally:
        client.close()


def test_parameters_are_read_set_and_followed_through_the_cloud(ros: tuple[str, Nodes], client: FoxgloveClient) -> None:
    master, _ = ros
    capabilities = client.wait("serverInfo")["info"]["capabilities"]
    assert {"parameters", "parametersSubscribe"} <= set(capabilities) and "time" not in capabilities

    client.command("getParameters", names=["/robot/gain"], id="g")
    answer = client.wait("parameterValues", lambda e: e.get("id") == "g")
    assert answer["parameters"] == [{"name": "/robot/gain", "value": 2.5, "type": "float64"}]

    client.command("subscribeParameterUpdates", names=["/robot/gain"])
    client.command("setParameters", parameters=[{"name": "/robot/gain", "value": 4, "type": "float64"}], id="s")
    assert client.wait("parameterValues", lambda e: e.get("id") == "s")["parameters"][0]["value"] == 4
    try:
        assert xmlrpc.client.ServerProxy(master).getParam("/test", "/robot/gain")[2] == 4.0
        xmlrpc.client.ServerProxy(master).setParam("/test", "/robot/gain", 6.5)  # a change behind its back
        update = client.wait("parameterValues", lambda e: e.get("id") is None and e["parameters"][0]["value"] == 6.5)
        assert update["parameters"] == [{"name": "/robot/gain", "value": 6.5, "type": "float64"}]

        bad = {"op": "setParameters", "parameters": [{"name": "/robot/gain", "value": {"x": 1}}]}
        client.command("raw", text=json.dumps(bad))
        assert client.status("parameters[0].value must be a number")["level"] == 2
        assert xmlrpc.client.ServerProxy(master).getParam("/test", "/robot/gain")[2] == 6.5
    finally:
        xmlrpc.client.ServerProxy(master).setParam("/test", "/robot/gain", 2.5)


def test_simulated_time_reaches_a_client_through_the_cloud(cloud: Server, ros: tuple[str, Nodes], robot: Bot) -> None:
    from bridgeos_agent.bridges.ros1graph import Ros1Graph

    master, _ = ros
    proxy = xmlrpc.client.ServerProxy(master)
    proxy.setParam("/test", "/use_sim_time", True)
    loop = LoopThread()

    async def simulate() -> tuple[Ros1Graph, asyncio.Task[Any]]:
        simulator = Ros1Graph(master, name="/relay_simulator")
        await simulator.start()
        clock = await simulator.advertise("/clock", "rosgraph_msgs/Clock")

        async def tick() -> None:
            nanoseconds = 5000 * 10**9
            while True:
                nanoseconds += 10**7
                clock.publish({"clock": {"secs": nanoseconds // 10**9, "nsecs": nanoseconds % 10**9}})
                await asyncio.sleep(0.01)

        return simulator, asyncio.get_running_loop().create_task(tick())

    simulator, ticking = loop.start(simulate()).result(15)
    client = FoxgloveClient(ticket(cloud, robot.id, robot.api_token)["foxglove_url"])
    try:
        assert "time" in client.wait("serverInfo")["info"]["capabilities"]
        stamps = [int(client.wait("time")["timestamp"]) for _ in range(3)]
        assert all(5000 * 10**9 < stamp < 6000 * 10**9 for stamp in stamps) and stamps[-1] > stamps[0]
    finally:
        client.close()
        proxy.deleteParam("/test", "/use_sim_time")

        async def stop() -> None:
            ticking.cancel()
            await simulator.close()

        loop.start(stop()).result(15)
        loop.stop()
