"""The cloud's /metrics: who may scrape it, and each family moving after a real action."""

from __future__ import annotations

import asyncio
import subprocess
from types import SimpleNamespace

import pytest
from asgiref.sync import sync_to_async
from django.conf import settings
from django.test import Client, override_settings

from bridgeos_agent.protocol import Event
from tests.cloud.wsutil import client_link, make_owner, make_robot, robot_link

from .promutil import fetch, promtool_check_metrics, value

pytestmark = [pytest.mark.django_db(transaction=True)]


def scrape(server) -> str:
    return fetch(server.url + "/metrics")


@pytest.mark.django_db
def test_metrics_are_refused_to_other_addresses_without_the_token():
    client = Client(REMOTE_ADDR="10.1.2.3")
    refused = client.get("/metrics")
    assert refused.status_code == 403
    assert b"BRIDGEOS_METRICS_TOKEN" in refused.content
    with override_settings(BRIDGEOS={**settings.BRIDGEOS, "METRICS_TOKEN": "s3cret"}):
        assert client.get("/metrics", HTTP_AUTHORIZATION="Bearer wrong").status_code == 403
        allowed = client.get("/metrics", HTTP_AUTHORIZATION="Bearer s3cret")
    assert allowed.status_code == 200
    assert allowed["Content-Type"].startswith("text/plain; version=0.0.4")
    assert b"bridgeos_robots_connected" in allowed.content


@pytest.mark.django_db
def test_metrics_are_served_to_loopback():
    answer = Client(REMOTE_ADDR="127.0.0.1").get("/metrics")
    assert answer.status_code == 200
    assert Client(REMOTE_ADDR="127.0.0.1").post("/metrics").status_code == 405


@pytest.mark.asyncio
async def test_a_connecting_robot_and_its_frames_are_counted(daphne_server):
    owner, _ = await make_owner("owner")
    before = await sync_to_async(scrape)(daphne_server)
    link = await robot_link(daphne_server, "prom-r1", await make_robot("prom-r1", owner))
    points = [{"name": "cpu", "value": i / 10, "ts": 1_700_000_000 + i} for i in range(50)]
    envelope = await link.send(Event.METRICS, {"metrics": points})
    await link.wait_acked(envelope)
    # The same frame again: a duplicate, acked and counted as a dedup hit.
    link.acked[envelope.id].clear()
    await link.send_envelope(envelope)
    await link.wait_acked(envelope)
    after = await sync_to_async(scrape)(daphne_server)

    assert value(after, "bridgeos_robot_connected", robot="prom-r1") == 1
    assert value(after, "bridgeos_robots_connected") >= 1
    assert value(after, "bridgeos_robot_last_seen_timestamp_seconds", robot="prom-r1") > 1_700_000_000
    assert value(after, "bridgeos_frames_received_total") - value(before, "bridgeos_frames_received_total") >= 2
    assert (
        value(after, "bridgeos_metric_points_received_total") - value(before, "bridgeos_metric_points_received_total")
        == 50
    )
    assert value(after, "bridgeos_dedup_hits_total") - value(before, "bridgeos_dedup_hits_total") == 1
    assert (
        value(after, "bridgeos_ingest_rows_written_total") - value(before, "bridgeos_ingest_rows_written_total") == 50
    )
    assert value(after, "bridgeos_ingest_batch_rows_count") > value(before, "bridgeos_ingest_batch_rows_count")
    assert value(after, "bridgeos_ingest_lag_seconds_count") > value(before, "bridgeos_ingest_lag_seconds_count")
    assert value(after, "bridgeos_http_request_seconds_count", route="metrics", method="GET", status="2xx") >= 1
    checked = promtool_check_metrics(after)
    assert checked.returncode == 0, checked.stdout + checked.stderr

    await link.close()
    await asyncio.sleep(0.5)
    gone = await sync_to_async(scrape)(daphne_server)
    assert value(gone, "bridgeos_robot_connected", robot="prom-r1") == 0


@pytest.mark.asyncio
async def test_commands_are_counted_by_outcome(daphne_server):
    alice, token = await make_owner("alice")
    robot_token = await make_robot("prom-bot", alice)
    client = await client_link(daphne_server, token)
    before = await sync_to_async(scrape)(daphne_server)
    assert value(before, "bridgeos_live_clients") >= 1

    offline = await client.request(Event.ROBOT_STOP, {"robot": "prom-bot"})
    assert offline.data["code"] == "robot_offline"

    robot = await robot_link(daphne_server, "prom-bot", robot_token)
    robot.auto_ack = False  # this robot answers by hand, or not at all
    refused = asyncio.ensure_future(client.request(Event.ROBOT_STOP, {"robot": "prom-bot"}))
    command = await robot.next(Event.ROBOT_STOP)
    await robot.send(Event.ERROR_MESSAGE, {"message": "not now", "code": "busy"}, reply_to=command.id)
    await refused
    accepted = asyncio.ensure_future(client.request(Event.ROBOT_STOP, {"robot": "prom-bot"}))
    command = await robot.next(Event.ROBOT_STOP)
    await robot.send(Event.ACK, {}, reply_to=command.id)
    await accepted
    # No answer at all: the cloud gives up after BRIDGEOS_COMMAND_WAIT_S (5 s).
    timed_out = await client.request(Event.ROBOT_STOP, {"robot": "prom-bot"}, timeout=15)
    assert timed_out.event == Event.ERROR_MESSAGE
    after = await sync_to_async(scrape)(daphne_server)

    for outcome in ("offline", "refused", "accepted", "timeout"):
        grown = value(after, "bridgeos_commands_total", outcome=outcome) - value(
            before, "bridgeos_commands_total", outcome=outcome
        )
        assert grown == 1, outcome
        assert value(after, "bridgeos_command_seconds_count", outcome=outcome) >= 1
    assert value(after, "bridgeos_command_seconds_sum", outcome="timeout") >= 5
    await robot.close()
    await client.close()


@pytest.fixture
def second_daphne(daphne_server, tmp_path):
    """Start a second daphne on the same database and the same Prometheus directory; yield its port."""
    from django.conf import settings as django_settings

    from tests.conftest import BIN, ROOT, free_port, service_env, wait_for_port

    port = free_port()
    env = service_env(django_settings.DATABASES["default"]["NAME"])
    assert env["PROMETHEUS_MULTIPROC_DIR"]  # shared by every process of this cloud
    with (tmp_path / "second.log").open("wb") as out:
        second = subprocess.Popen(
            [str(ROOT / "scripts" / "daphne"), "-b", "127.0.0.1", "-p", str(port)],
            cwd=ROOT,
            env={**env, "VIRTUAL_ENV": str(BIN.parent)},
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    try:
        wait_for_port(port, second)
        yield port
    finally:
        second.terminate()
        second.wait(timeout=15)


@pytest.mark.asyncio
async def test_any_daphne_serves_the_sum_of_all_processes(daphne_server, second_daphne):
    owner, _ = await make_owner("owner-two")
    token = await make_robot("prom-two", owner)
    before = await sync_to_async(scrape)(daphne_server)
    # The robot talks to the second daphne; the first one's /metrics counts its points.
    link = await robot_link(SimpleNamespace(ws_url=f"ws://127.0.0.1:{second_daphne}"), "prom-two", token)
    envelope = await link.send(Event.METRICS, {"metrics": [{"name": "cpu", "value": 1.0, "ts": 1_700_000_000}]})
    await link.wait_acked(envelope)
    await link.close()
    after = await sync_to_async(scrape)(daphne_server)
    grown = value(after, "bridgeos_metric_points_received_total") - value(
        before, "bridgeos_metric_points_received_total"
    )
    assert grown == 1
