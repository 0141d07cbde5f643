"""The agent's --metrics endpoint, each family asserted after a real action against the real cloud."""

from __future__ import annotations

import asyncio

import httpx
import pytest

from bridgeos_agent import metrics
from bridgeos_agent.cli import main
from bridgeos_agent.controller import RobotController
from bridgeos_agent.skillconfig import parse_skill_config
from tests.agent.conftest import (
    agent_settings,
    cloud,  # noqa: F401  (the fixture: a daphne of the test's own, with a Celery worker)
    make_robot,
    running,
)
from tests.conftest import eventually, free_port

from .promutil import promtool_check_metrics, value

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(240)]

SKILL = "observed"


def observed_skill() -> dict:
    """A Skill with a component that keeps crashing and one whose cloud copy cannot start."""
    components = {
        "crasher": {
            "name": "Crasher",
            "location": "robot",
            "ros": False,
            "resources": {"cpu": 0.1, "ram": 16},
            "robot": {"command": ["sh", "-c", "sleep 0.5; exit 3"]},
        },
        "mover": {
            "name": "Mover",
            "location": "either",
            "ros": False,
            "resources": {"cpu": 0.1, "ram": 16},
            "robot": {"command": ["sleep", "600"]},
            "cloud": {"command": ["/nonexistent/bridgeos-test-binary"]},
        },
    }
    config = {"skill": "Observed", "skill_id": SKILL, "manager": {"decision_interval": 1}, "components": components}
    return parse_skill_config(config).model_dump(mode="json")


def test_metrics_address_must_be_host_and_port():
    assert metrics.parse_address("127.0.0.1:9101") == ("127.0.0.1", 9101)
    assert metrics.parse_address("[::1]:9101") == ("::1", 9101)
    for bad in ("9101", ":9101", "host:", "host:http", "host:70000"):
        with pytest.raises(ValueError):
            metrics.parse_address(bad)
    assert main(["run", "--master", "ws://127.0.0.1:1", "--robot", "r", "--token", "t", "--metrics", "nope"]) == 2


async def test_the_agent_counts_links_outbox_decisions_migrations_and_restarts(cloud, tmp_path):  # noqa: F811
    token, api_token = await make_robot("obs-1", skill=observed_skill())
    controller = RobotController(agent_settings(cloud, "obs-1", token, tmp_path / "agent", cloud_start_timeout=20))
    address = f"127.0.0.1:{free_port()}"
    exporter = await metrics.serve(controller, address)
    headers = {"Authorization": f"Token {api_token}"}
    try:
        async with (
            running(controller),
            httpx.AsyncClient(base_url=cloud.url, headers=headers, timeout=60) as api,
            httpx.AsyncClient(base_url=f"http://{address}") as scraper,
        ):

            async def scrape() -> str:
                return (await scraper.get("/metrics")).text

            await asyncio.wait_for(controller.config_from_cloud.wait(), 15)
            text = await scrape()
            assert value(text, "bridgeos_agent_link_up", robot="obs-1") == 1
            assert value(text, "bridgeos_agent_reconnects_total", robot="obs-1") == 0

            assert (await api.post(f"/api/robot/obs-1/skill/{SKILL}/start", params={"wait": 10})).status_code == 200

            async def restarted() -> bool:
                return value(await scrape(), "bridgeos_agent_component_restarts_total", component="crasher") >= 1

            await eventually(restarted, what="the crashing component restarted")

            async def decided() -> bool:
                return value(await scrape(), "bridgeos_agent_decisions_total", skill=SKILL) >= 1

            await eventually(decided, what="the manager decided")

            # Moving the mover to the cloud fails: its cloud copy cannot start there.
            path = f"/api/robot/obs-1/skill/{SKILL}/component/mover/migrate"
            await api.post(path, params={"wait": 30})

            async def failed() -> bool:
                return value(await scrape(), "bridgeos_agent_migrations_total", skill=SKILL, outcome="failed") >= 1

            await eventually(failed, timeout=60, what="the failed migration counted")
            # The cloud's side of it: the Celery worker's start task and the copy's state, on the cloud's /metrics.
            cloud_text = (await api.get("/metrics")).text
            assert value(cloud_text, "bridgeos_celery_tasks_total", task="skills.tasks.start_cloud_component") >= 1
            assert value(cloud_text, "bridgeos_cloud_copies") >= 1

            # The cloud goes away: the link drops and the outbox holds the frames, getting older.
            cloud.stop()

            async def held() -> bool:
                text = await scrape()
                return (
                    value(text, "bridgeos_agent_link_up") == 0
                    and value(text, "bridgeos_agent_outbox_frames") > 0
                    and value(text, "bridgeos_agent_outbox_oldest_age_seconds") > 0.5
                )

            await eventually(held, what="frames held while the cloud is away")
            cloud.start()

            async def reconnected() -> bool:
                text = await scrape()
                return (
                    value(text, "bridgeos_agent_reconnects_total") >= 1 and value(text, "bridgeos_agent_link_up") == 1
                )

            await eventually(reconnected, what="reconnected")
            checked = promtool_check_metrics(await scrape())
            assert checked.returncode == 0, checked.stdout + checked.stderr
    finally:
        await exporter.cleanup()
