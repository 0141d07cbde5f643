"""People detection with the thesis's 30-40 MB pointclouds (§5.3.1) through the real Skill Router.

The real ``bridgeos-usecase`` nodes run in their component instances' namespaces, the
sample Skill's router relays every topic between them over TCPROS, and a probe listens on
the canonical ``/people`` the router publishes: a 35 MB cloud goes publisher → router →
sampler (cloud instance) → router → detector (cloud instance) → router → probe.
"""

from __future__ import annotations

import asyncio
import math
import re
import time
from collections.abc import AsyncIterator

import pytest

from bridgeos_agent.rosnames import instance_namespace
from bridgeos_agent.router import RouterSettings, SkillRouter
from bridgeos_agent.skillconfig import load_sample_skill_config
from tests.usecases.conftest import Nodes, RosMaster
from tests.usecases.test_nodes import PEOPLE_PROBE

pytestmark = [pytest.mark.ros, pytest.mark.timeout(120)]

PEOPLE = [(2.5, 0.8), (4.0, -1.0), (5.5, 0.6)]
MEGABYTES = 35


@pytest.fixture
async def router(ros_master: RosMaster) -> AsyncIterator[SkillRouter]:
    """Run the people detection sample's Skill Router, sampler and detector active in the cloud."""
    config = load_sample_skill_config("people_detection")
    router = SkillRouter(config, ros_master=ros_master.uri, settings=RouterSettings(http_host="127.0.0.1"))
    for component, location in {"pointcloud": "robot", "sampler": "cloud", "detector": "cloud"}.items():
        router.set_active(component, location)
    await router.start()
    try:
        yield router
    finally:
        await router.close()


async def test_a_35_mb_cloud_crosses_the_router_and_the_detector_answers(nodes: Nodes, router: SkillRouter) -> None:
    began = time.monotonic()
    skill = router.config.skill_id
    nodes.start("sampler", "sampler", "--voxel", "0.05", namespace=instance_namespace(skill, "sampler", "cloud"))
    nodes.start("detector", "detector", namespace=instance_namespace(skill, "detector", "cloud"))
    assert await router.wait_ready("sampler", "cloud", 30), nodes.all_logs()
    spots = ";".join(f"{x},{y}" for x, y in PEOPLE)
    nodes.start(
        "pointcloud",
        "pointcloud",
        "--megabytes",
        str(MEGABYTES),
        "--rate",
        "0.5",
        "--people",
        spots,
        namespace=instance_namespace(skill, "pointcloud", "robot"),
    )

    # The detections on the canonical /people, which only the router publishes.
    found = await asyncio.to_thread(nodes.probe, PEOPLE_PROBE, "50", timeout=55)

    assert len(found) == len(PEOPLE), f"detected {found}, placed {PEOPLE}\n{nodes.all_logs()}"
    for x, y in PEOPLE:
        assert min(math.dist((x, y), tuple(d)) for d in found) < 0.35, f"no detection near {(x, y)}: {found}"
    size = re.search(r"cloud, ([\d.]+) MB", nodes.log("pointcloud"))
    assert size and 33 <= float(size[1]) <= 37, nodes.log("pointcloud")
    stats = router.statistics()
    cloud, sampled, people = stats["/pointcloud"], stats["/pointcloud_sampled"], stats["/people"]
    assert cloud["subscribers"]["sampler"]["messages"] >= 1 and cloud["dropped"] == 0
    assert cloud["bytes"] >= MEGABYTES * 1e6 * 0.95 * cloud["messages"]
    assert sampled["subscribers"]["detector"]["messages"] >= 1 and people["messages"] >= 1
    # The camera's stamp to the detections, the thesis's processing time: no stall on the way.
    latency = nodes.wait_for("detector", r"metric pointcloud_processing_ms=([\d.]+)", timeout=10)
    assert float(latency[1]) < 20_000, nodes.all_logs()
    assert time.monotonic() - began < 60
