"""MCAP recordings end to end: a real agent, a live cloud (daphne), real rospy and rclpy talkers, the mcap reader."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import io
import json
import os
import shutil
import subprocess
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from asgiref.sync import sync_to_async
from mcap.reader import make_reader

from bridgeos_agent.bridges.recorder import Recordings
from bridgeos_agent.controller import AgentSettings, RobotController
from bridgeos_agent.ros2graph import rclpy_missing
from tests.agent.conftest import Cloud
from tests.agent.ros2helpers import Ros2Nodes, loopback_graph
from tests.agent.roshelpers import HOST_PYTHON, Nodes, private_rosmaster
from tests.conftest import ROOT, close_other_sessions, eventually

MCAP_JS = ROOT / "tests" / "js" / "mcap"  # Foxglove's MCAP reader, installed by scripts/services.sh node

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(120)]

needs_ros1 = pytest.mark.skipif(
    not (Path(HOST_PYTHON).exists() and Path("/usr/bin/rosmaster").exists()), reason="needs Debian's ROS 1"
)


@sync_to_async
def make_robot(robot_id: str) -> tuple[str, str, str]:
    """Create a robot; return its token, its owner's API token and another user's API token."""
    from django.contrib.auth import get_user_model

    from robots.services import create_robot, issue_api_token

    users = get_user_model().objects
    owner = users.create_user(f"owner-{robot_id}")
    stranger = users.create_user(f"stranger-{robot_id}")
    _, token = create_robot(robot_id, owner)
    return token, issue_api_token(owner)[0], issue_api_token(stranger)[0]


@pytest.fixture(scope="session")
def sessions_closed_at_the_end(django_db_setup: Any, django_db_blocker: Any) -> Any:
    yield
    with django_db_blocker.unblock():
        close_other_sessions()  # the killed daphnes' leftovers, so the test database can be dropped


@pytest.fixture
def cloud(tmp_path: Path, sessions_closed_at_the_end: Any) -> Any:
    server = Cloud(tmp_path / "daphne.log")
    server.env = {"BRIDGEOS_RECORDINGS_DIR": str(tmp_path / "recordings")}
    server.start()
    yield server
    server.stop()


@contextlib.asynccontextmanager
async def agent(cloud: Cloud, robot: str, token: str, data_dir: Path, **kw: Any) -> AsyncIterator[RobotController]:
    """Run a connected agent; its recordings send small chunks, so even a short one crosses the link in many."""
    controller = RobotController(
        AgentSettings(
            master=cloud.ws_url,
            robot=robot,
            token=token,
            data_dir=data_dir,
            simulate=True,
            reconnect_initial=0.2,
            reconnect_max=0.5,
            **kw,
        )
    )
    controller.recordings = Recordings(controller, chunk_bytes=512, mcap_chunk_size=1024)
    task = asyncio.create_task(controller.run())
    try:
        await eventually(controller.connected.is_set, what="the agent connected")
        yield controller
    finally:
        controller.stop()
        await asyncio.wait_for(task, 30)


def foxglove_reads(data: bytes, directory: Path) -> dict[str, Any]:
    """Read an MCAP file with Foxglove's own reader (@mcap/core, zstd by @foxglove/wasm-zstd) under Node."""
    if not (shutil.which("node") and (MCAP_JS / "node_modules" / "@mcap" / "core").is_dir()):
        pytest.skip("Node and tests/js/mcap's packages are needed: bash scripts/services.sh node")
    path = directory / "foxglove-reads.mcap"
    path.write_bytes(data)
    done = subprocess.run(["node", str(MCAP_JS / "read.mjs"), str(path)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def api(cloud: Cloud, token: str) -> httpx.AsyncClient:
    return httpx.AsyncClient(base_url=cloud.url, headers={"Authorization": f"Token {token}"}, timeout=30)


async def start(client: httpx.AsyncClient, robot: str, **body: Any) -> httpx.Response:
    return await client.post(f"/api/robot/{robot}/recordings?wait=15", json=body)


async def start_once_known(client: httpx.AsyncClient, robot: str, **body: Any) -> dict[str, Any]:
    """Start a recording as soon as the robot's graph knows its topics (a talker takes a moment to appear)."""
    deadline = time.monotonic() + 30
    while True:
        answer = await start(client, robot, **body)
        if answer.status_code == 201:
            return answer.json()
        assert answer.status_code == 400 and "unknown topic" in answer.text, answer.text
        assert time.monotonic() < deadline, answer.text
        await asyncio.sleep(0.2)


async def finished(client: httpx.AsyncClient, robot: str, recording: str, timeout: float = 30) -> dict[str, Any]:
    async def done() -> dict[str, Any] | None:
        answer = (await client.get(f"/api/robot/{robot}/recordings/{recording}")).json()
        return answer if answer["status"] in ("finished", "failed") else None

    return await eventually(done, timeout, what=f"recording {recording} assembled")


async def download(client: httpx.AsyncClient, robot: str, recording: str) -> bytes:
    answer = await client.get(f"/api/robot/{robot}/recordings/{recording}/download")
    assert answer.status_code == 200, answer.text
    assert answer.headers["content-disposition"].endswith(f'{robot}-{recording}.mcap"')
    return answer.content


def read_back(data: bytes, decoder: Any) -> tuple[Any, list[tuple[Any, Any, Any, Any]]]:
    """Read an MCAP file with mcap's reader: its header and every message decoded."""
    reader = make_reader(io.BytesIO(data), decoder_factories=[decoder])
    return reader.get_header(), list(reader.iter_decoded_messages())


def seqs(messages: list[tuple[Any, Any, Any, Any]], tag: str) -> list[int]:
    return [int(m.data.split()[1]) for _, _, _, m in messages if m.data.startswith(tag + " ")]


@sync_to_async
def robot_page(robot: str, username: str) -> str:
    """Render the dashboard's page of a robot for a user (server-rendered, as the browser gets it)."""
    from django.contrib.auth import get_user_model
    from django.test import Client

    client = Client()
    client.force_login(get_user_model().objects.get(username=username))
    answer = client.get(f"/robots/{robot}/")
    assert answer.status_code == 200
    return answer.content.decode()


def chunk_frames_held(controller: RobotController) -> int:
    return sum('"recording_chunk"' in text for _, _, text in controller.outbox.backlog())


# --------------------------------------------------------------------------- ROS 1


@needs_ros1
async def test_a_ros1_recording_survives_a_cloud_outage_and_reads_back_whole(cloud, tmp_path, monkeypatch):
    from mcap_ros1.decoder import DecoderFactory

    token, owner, _ = await make_robot("rec-1")
    with private_rosmaster(tmp_path) as master:
        monkeypatch.setenv("ROS_MASTER_URI", master)
        nodes = Nodes(master, tmp_path)
        try:
            async with (
                agent(cloud, "rec-1", token, tmp_path / "agent", ros2="off") as controller,
                api(cloud, owner) as client,
            ):
                answer = await start(client, "rec-1", topics=["/counted"], max_duration_s=120)
                # /counted has no publisher yet: the robot does not know it and says so; nothing is kept.
                assert answer.status_code == 400 and "/counted" in answer.json()["topics"][0], answer.text
                assert (await client.get("/api/robot/rec-1/recordings")).json() == []

                # The talker waits for a subscriber: the recording is its first.
                nodes.run(
                    "talker",
                    "talker",
                    "--topic",
                    "/counted",
                    "--tag",
                    "c",
                    "--rate",
                    "40",
                    "--count",
                    "160",
                    "--size",
                    "200",
                    "--wait",
                )
                recording = await start_once_known(client, "rec-1", topics=["/counted"], max_duration_s=120)
                assert recording["status"] in ("starting", "recording") and recording["ros"] == ""

                def recorded() -> int:
                    active = controller.recordings.active.get(recording["id"])
                    return active.mcap.messages if active is not None else 0

                await eventually(lambda: recorded() > 30, what="messages recorded")

                cloud.stop()  # the cloud crashes mid-recording
                await eventually(lambda: not controller.connected.is_set(), what="the agent notices")
                await eventually(lambda: chunk_frames_held(controller) >= 3, what="chunks kept on disk while away")
                cloud.start()
                await eventually(lambda: "sent 160" in nodes.lines("talker"), what="the talker done", timeout=60)
                await eventually(controller.connected.is_set, what="the agent back")

                answer = await client.post(f"/api/robot/rec-1/recordings/{recording['id']}/stop?wait=15")
                assert answer.status_code == 200 and answer.json()["status"] in ("stopping", "finished"), answer.text
                done = await finished(client, "rec-1", recording["id"])
                assert done["status"] == "finished" and done["message"] == "stopped", done
                assert done["message_count"] == 160 and done["ros"] == "ros1"
                assert done["download"].endswith(f"/api/robot/rec-1/recordings/{recording['id']}/download")
                data = await download(client, "rec-1", recording["id"])
                assert len(data) == done["size_bytes"]
                assert chunk_frames_held(controller) == 0

            header, messages = read_back(data, DecoderFactory())
            assert header.profile == "ros1"
            assert seqs(messages, "c") == list(range(1, 161))  # every message, once, in order: no hole
            schema, channel = messages[0][0], messages[0][1]
            assert (schema.name, schema.encoding, channel.topic, channel.message_encoding) == (
                "std_msgs/String",
                "ros1msg",
                "/counted",
                "ros1",
            )
            assert schema.data.decode().strip() == "string data"
            seen = foxglove_reads(data, tmp_path)
            assert (seen["profile"], seen["counts"], seen["statistics"]) == (
                "ros1",
                {"/counted": 160},
                {"messageCount": 160},
            )
            assert seen["channels"][0]["schema"] == {
                "name": "std_msgs/String",
                "encoding": "ros1msg",
                "data": "string data\n",
            }
            assert base64.b64decode(seen["first"]["bytes"]) == messages[0][2].data
        finally:
            nodes.kill_all()


@needs_ros1
async def test_limits_end_a_recording_and_bad_input_or_another_user_changes_nothing(cloud, tmp_path, monkeypatch):
    from mcap_ros1.decoder import DecoderFactory

    token, owner, stranger = await make_robot("rec-2")
    with private_rosmaster(tmp_path) as master:
        monkeypatch.setenv("ROS_MASTER_URI", master)
        nodes = Nodes(master, tmp_path)
        nodes.run("steady", "talker", "--topic", "/steady", "--tag", "s", "--rate", "50", "--size", "100")
        try:
            async with agent(cloud, "rec-2", token, tmp_path / "agent", ros2="off"), api(cloud, owner) as client:
                # The size limit: each message is ~120 bytes, so 3000 bytes hold about 25 of them.
                started = await start_once_known(client, "rec-2", topics=["/steady"], max_bytes=3000)
                by_size = await finished(client, "rec-2", started["id"])
                assert by_size["status"] == "finished" and by_size["message"] == "size limit reached", by_size
                assert 0 < by_size["data_bytes"] <= 3000 and by_size["message_count"] >= 20
                _, messages = read_back(await download(client, "rec-2", by_size["id"]), DecoderFactory())
                assert len(messages) == by_size["message_count"]
                assert sum(len(m.data) + 4 for _, _, _, m in messages) == by_size["data_bytes"]
                page = await robot_page("rec-2", "owner-rec-2")
                assert f'href="/api/robot/rec-2/recordings/{by_size["id"]}/download"' in page
                assert "size limit reached" in page

                # The duration limit.
                answer = await start(client, "rec-2", topics=["/steady"], max_duration_s=1.0)
                assert answer.status_code == 201, answer.text
                by_time = await finished(client, "rec-2", answer.json()["id"])
                assert by_time["message"] == "duration limit reached", by_time
                assert 0.9 <= by_time["duration_s"] <= 3.0 and 10 <= by_time["message_count"] <= 100

                # One at a time: a second start while one runs is refused, and nothing is added.
                running = await start(client, "rec-2", topics=["/steady"])
                assert running.status_code == 201
                rid = running.json()["id"]
                # Once the robot said it records: what follows must change nothing, its own progress included.
                deadline = time.monotonic() + 15
                while (await client.get(f"/api/robot/rec-2/recordings/{rid}")).json()["status"] != "recording":
                    assert time.monotonic() < deadline, "the recording never started"
                    await asyncio.sleep(0.1)
                before = (await client.get("/api/robot/rec-2/recordings")).json()
                newest = (await client.get("/api/robot/rec-2/recordings?limit=1")).json()
                assert [r["id"] for r in newest] == [before[0]["id"]] and len(before) >= 2
                for bad in ("0", "1001", "x", "-1"):
                    answer = await client.get(f"/api/robot/rec-2/recordings?limit={bad}")
                    assert answer.status_code == 400 and "limit" in answer.json(), answer.text
                bad = [
                    ({"topics": ["/steady"]}, "non_field_errors", "already running"),
                    ({"topics": []}, "topics", ""),
                    ({"topics": ["chatter"]}, "topics", "absolute"),
                    ({"topics": ["/steady", "/steady"]}, "topics", "once"),
                    ({"topics": ["/steady"], "max_bytes": 10}, "max_bytes", ""),
                    ({"topics": ["/steady"], "max_duration_s": 0}, "max_duration_s", ""),
                    ({"topics": ["/steady"], "max_duration_s": 1e9}, "max_duration_s", ""),
                    ({"topics": ["/steady"], "ros": "ros3"}, "ros", ""),
                ]
                for body, field, says in bad:
                    answer = await start(client, "rec-2", **body)
                    assert answer.status_code == 400, (body, answer.text)
                    assert says in str(answer.json()[field]), (body, answer.text)
                answer = await client.delete(f"/api/robot/rec-2/recordings/{rid}")
                assert answer.status_code == 400 and "stop it first" in answer.text
                assert (await client.get(f"/api/robot/rec-2/recordings/{rid}/download")).status_code == 409
                assert (await client.get("/api/robot/rec-2/recordings")).json() == before

                # Another user's token: every endpoint answers 404, as if the robot did not exist.
                async with api(cloud, stranger) as other:
                    base = "/api/robot/rec-2/recordings"
                    for method, path in [
                        ("GET", base),
                        ("POST", base),
                        ("GET", f"{base}/{rid}"),
                        ("DELETE", f"{base}/{rid}"),
                        ("POST", f"{base}/{rid}/stop"),
                        ("GET", f"{base}/{rid}/download"),
                        ("GET", f"{base}/{by_size['id']}/download"),
                    ]:
                        answer = await other.request(
                            method, path, json={"topics": ["/steady"]} if method == "POST" else None
                        )
                        assert answer.status_code == 404, (method, path, answer.status_code)
                assert (await client.get("/api/robot/rec-2/recordings")).json() == before

                answer = await client.post(f"{base}/{rid}/stop?wait=15")
                assert answer.status_code == 200, answer.text
                await finished(client, "rec-2", rid)
                answer = await client.post(f"{base}/{rid}/stop")
                assert answer.status_code == 400 and "not running" in answer.text
                folder = tmp_path / "recordings" / "rec-2" / rid
                assert (folder / "recording.mcap").is_file()
                assert (await client.delete(f"{base}/{rid}")).status_code == 204
                assert (await client.get(f"{base}/{rid}")).status_code == 404
                await eventually(lambda: not folder.exists(), what="the file deleted")
        finally:
            nodes.kill_all()


# --------------------------------------------------------------------------- ROS 2


@pytest.mark.skipif(bool(rclpy_missing()), reason="needs rclpy")
async def test_a_ros2_recording_carries_cdr_with_its_ros2msg_schema(cloud, tmp_path, monkeypatch):
    from mcap_ros2.decoder import DecoderFactory

    graph = loopback_graph()
    for name, value in graph.env().items():
        monkeypatch.setenv(name, value)
    token, owner, _ = await make_robot("rec-3")
    nodes = Ros2Nodes(graph, tmp_path)
    topic = f"/rec_chatter_{os.getpid()}"
    try:
        async with (
            agent(cloud, "rec-3", token, tmp_path / "agent", ros2="on", detect_ros_master=False),
            api(cloud, owner) as client,
        ):
            nodes.run(
                "talker",
                "talker",
                "--topic",
                topic,
                "--tag",
                "r",
                "--rate",
                "50",
                "--count",
                "60",
                "--wait",
                "--settle",
                "0.5",
                "--linger",
                "5",
            )
            recording = (await start_once_known(client, "rec-3", topics=[topic], ros="ros2"))["id"]
            await eventually(lambda: "sent 60" in nodes.lines("talker"), what="the talker done")
            await asyncio.sleep(0.5)
            answer = await client.post(f"/api/robot/rec-3/recordings/{recording}/stop?wait=15")
            assert answer.status_code == 200, answer.text
            done = await finished(client, "rec-3", recording)
            assert done["status"] == "finished" and done["message_count"] == 60 and done["ros"] == "ros2", done
            data = await download(client, "rec-3", recording)
        header, messages = read_back(data, DecoderFactory())
        assert header.profile == "ros2"
        assert seqs(messages, "r") == list(range(1, 61))
        schema, channel = messages[0][0], messages[0][1]
        assert (schema.name, schema.encoding, channel.message_encoding) == ("std_msgs/msg/String", "ros2msg", "cdr")
        assert "string data" in schema.data.decode()
        seen = foxglove_reads(data, tmp_path)
        assert (seen["profile"], seen["counts"]) == ("ros2", {topic: 60})
        assert seen["channels"][0]["messageEncoding"] == "cdr"
        assert seen["channels"][0]["schema"]["name"] == "std_msgs/msg/String"
    finally:
        nodes.kill_all()


@needs_ros1
async def test_a_recording_cut_short_by_an_agent_crash_is_ended_on_restart_from_the_chunks_it_sent(
    cloud, tmp_path, monkeypatch
):
    from mcap_ros1.decoder import DecoderFactory

    token, owner, _ = await make_robot("rec-4")
    with private_rosmaster(tmp_path) as master:
        monkeypatch.setenv("ROS_MASTER_URI", master)
        nodes = Nodes(master, tmp_path)
        nodes.run("talker", "talker", "--topic", "/cut", "--tag", "k", "--rate", "40", "--size", "200")
        try:
            async with api(cloud, owner) as client:
                async with agent(cloud, "rec-4", token, tmp_path / "agent", ros2="off") as controller:
                    recording = (await start_once_known(client, "rec-4", topics=["/cut"], max_duration_s=120))["id"]

                    def sent() -> int:
                        active = controller.recordings.active.get(recording)
                        return active.seq if active is not None else 0

                    await eventually(lambda: sent() >= 4, what="chunks sent to the cloud")
                    cloud.stop()  # more chunks wait in the outbox, then the agent dies with them there
                    await eventually(lambda: chunk_frames_held(controller) >= 3, what="chunks kept on disk while away")

                    held = chunk_frames_held(controller)

                    async def killed() -> None:
                        # What a SIGKILL leaves: no last chunks, no final status; the senders just stop.
                        await controller.recordings.tasks.close()
                        for graph in controller.recordings._graphs.values():
                            await graph.close()  # only so this test process does not keep the node

                    controller.recordings.close = killed  # type: ignore[method-assign]
                assert (tmp_path / "agent" / "recordings" / f"{recording}.json").exists()

                cloud.start()
                async with agent(cloud, "rec-4", token, tmp_path / "agent", ros2="off") as restarted:
                    done = await finished(client, "rec-4", recording)
                    assert not (tmp_path / "agent" / "recordings" / f"{recording}.json").exists()
                    await eventually(lambda: chunk_frames_held(restarted) == 0, what="the outbox emptied")
                assert done["status"] == "failed" and done["message"].startswith("cut short"), done
                assert held >= 3
                data = await download(client, "rec-4", recording)
                assert len(data) == done["size_bytes"]
                # A second stop is refused: the recording has ended.
                answer = await client.post(f"/api/robot/rec-4/recordings/{recording}/stop?wait=5")
                assert answer.status_code == 400, answer.text
                # Deleting the robot deletes its recordings' files with their rows.
                folder = tmp_path / "recordings" / "rec-4"
                assert (folder / recording / "recording.mcap").is_file()
                assert (await client.delete("/api/robot/rec-4")).status_code == 204
                await eventually(lambda: not folder.exists(), what="the robot's recordings' files deleted")

            header, messages = read_back(data, DecoderFactory())
            assert header.profile == "ros1"
            got = seqs(messages, "k")
            # Whatever reached the outbox, from the recording's first message on, without a hole.
            assert len(got) == done["message_count"] > 20, (len(got), done)
            assert got == list(range(got[0], got[0] + len(got)))
            assert done["duration_s"] is not None and done["duration_s"] > 0.3
        finally:
            nodes.kill_all()
