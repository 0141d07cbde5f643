"""Two thousand robots on one daphne, and a real agent among them: the suite's short form of benchmarks/tenk.py.

The fleet is benchmarks/_multifleet.py's: one process multiplexing every robot over the real wire
protocol and authentication. The real agent, connected to the same daphne, is the reference: what
the cloud does for it (connected, its metrics stored, a command answered) it does for the fleet.
"""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import httpx
import pytest
from django.contrib.auth import get_user_model

from benchmarks._multifleet import FleetProcess
from monitoring.models import Metric
from robots.models import Robot, default_robot_config
from robots.services import issue_api_token
from teams.services import personal_organization
from tests.conftest import BIN, another_daphne, stop_process, wait_until
from tests.logguard import watch

pytestmark = pytest.mark.django_db(transaction=True)

FLEET = 2000
VANISH = 200
AGENT = "reference-agent"
# daphne pings a robot silent for 2 s and drops it 3 s later: a vanished robot is offline within ~7 s
# (its checker runs every 2 s), where production's 20 + 30 s would outlast the test.
PING_INTERVAL_S, PING_TIMEOUT_S = 2, 3


def make_fleet() -> tuple[list[tuple[str, str]], str, str]:
    """Create the fleet and the agent's robot; return the fleet's (id, token) pairs, the agent's token and an API key."""
    owner = get_user_model().objects.create_user("fleet2k-owner")
    organization = personal_organization(owner)
    config = default_robot_config()
    rows, tokens = [], []
    for i in range(FLEET + 1):
        robot = Robot(id=f"fleet2k-{i:04d}" if i < FLEET else AGENT, owner=owner, organization=organization)
        robot.config = config
        tokens.append((robot.id, robot.issue_token()))
        rows.append(robot)
    Robot.objects.bulk_create(rows, batch_size=1000)
    key, _ = issue_api_token(owner)
    return tokens[:FLEET], tokens[FLEET][1], key


def start_agent(master: str, token: str, data_dir: Path, log: Path) -> subprocess.Popen:
    """Start the real agent, simulated, against the fleet's daphne."""
    token_file = data_dir.parent / "agent.token"
    token_file.write_text(token + "\n")
    token_file.chmod(0o600)
    command = [
        str(BIN / "bridgeos-agent"),
        "run",
        "--master",
        master,
        "--robot",
        AGENT,
        "--token-file",
        str(token_file),
    ]
    command += ["--runtime", "process", "--simulate", "--data-dir", str(data_dir)]
    env = {key: value for key, value in os.environ.items() if key != "BRIDGEOS_TOKEN"}
    with watch(log).open("ab") as out:
        return subprocess.Popen(command, env={**env, "PYTHONUNBUFFERED": "1"}, stdout=out, stderr=subprocess.STDOUT)


def connected_ids() -> set[str]:
    return set(Robot.objects.filter(connected=True).values_list("id", flat=True))


def stored_points(prefix: str) -> int:
    return Metric.objects.filter(robot__id__startswith=prefix).count()


def test_two_thousand_robots_connect_report_and_are_honestly_present(tmp_path):
    started = time.monotonic()
    tokens, agent_token, key = make_fleet()
    env = {"BRIDGEOS_WS_PING_INTERVAL": str(PING_INTERVAL_S), "BRIDGEOS_WS_PING_TIMEOUT": str(PING_TIMEOUT_S)}
    with another_daphne(tmp_path / "daphne.log", **env) as (server, _):
        agent = start_agent(server.ws_url, agent_token, tmp_path / "agent-data", tmp_path / "agent.log")
        fleet = FleetProcess(tokens, [server.ws_url])
        try:
            # All at once, none rejected: every handshake accepted and every login answered.
            connect = fleet.ask("connect", timeout=120, within_s=90)
            assert connect["rejected"] == 0, connect["failures"]
            assert connect["connected"] == FLEET
            wait_until(lambda: len(connected_ids()) == FLEET + 1, timeout=60, what="every row to say connected")

            # Every robot reports 3 points a second for 3 s: every point stored once, every frame acked.
            report = fleet.ask("ingest", timeout=120, seconds=3.0, points_per_frame=3, every_s=1.0, drain_s=30.0)
            assert report["unacked_frames"] == 0
            assert report["points_sent"] >= FLEET * 3 * 2
            assert stored_points("fleet2k-") == report["points_sent"]
            # The real agent samples every second; its points are stored the same way.
            wait_until(lambda: stored_points(AGENT) > 0, timeout=30, what="the agent's metrics")

            # A command among them, to a simulated robot and to the real agent: both answer.
            with httpx.Client(base_url=server.url, headers={"Authorization": f"Token {key}"}, timeout=30) as http:
                for robot_id in ("fleet2k-1234", AGENT):
                    answer = http.post(f"/api/robot/{robot_id}/start", params={"wait": "10"})
                    assert answer.status_code == 200, answer.text
                    assert answer.json()["accepted"] is True
                # And one command to the whole fleet: every robot's answer in one response.
                answer = http.post("/api/robot/start", params={"wait": "30"}, timeout=60)
                assert answer.status_code == 200, answer.text
                refused = [result for result in answer.json()["results"] if not result["accepted"]]
                assert len(answer.json()["results"]) == FLEET + 1 and not refused, refused[:3]

            # 200 robots vanish without a goodbye: offline within the ping interval and timeout, the rest not.
            gone = set(fleet.ask("vanish", robots=VANISH)["robots"])
            assert len(gone) == VANISH
            wait_until(
                lambda: not gone & connected_ids(),
                timeout=PING_INTERVAL_S + PING_TIMEOUT_S + 15,
                what="the vanished robots to be marked disconnected",
            )
            assert len(connected_ids()) == FLEET + 1 - VANISH
        finally:
            fleet.stop()
            stop_process(agent)
    assert time.monotonic() - started < 120
