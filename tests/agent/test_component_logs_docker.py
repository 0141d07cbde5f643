"""Component logs from the Docker runtime: Docker's log stream, its timestamps, across an agent restart."""

from __future__ import annotations

import asyncio
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from docker.api import APIClient

from bridgeos_agent.logs.service import ComponentLogService
from bridgeos_agent.runtime import ComponentSpec, RestartPolicy, Status
from bridgeos_agent.runtime.docker import DockerRuntime
from bridgeos_agent.skillconfig import ComponentResources, LaunchSpec
from tests.conftest import eventually

pytestmark = pytest.mark.docker

IMAGE = "bridgeos/base:bookworm"
TICKS = 'echo "[INFO] [1.0]: up"; echo "ERROR:cam:no frames" >&2; i=0; while true; do i=$((i+1)); echo "tick $i"; sleep 0.01; done'


@pytest.fixture(scope="module")
def api() -> Iterator[APIClient]:
    try:
        client = APIClient(version="auto", timeout=10)
        client.ping()
    except Exception:
        pytest.skip("dockerd is not running (`docker info` fails): start it with `sudo scripts/services.sh docker`")
    yield client
    client.close()


@pytest.fixture
def robot(api: APIClient) -> Iterator[str]:
    robot = f"tlogs{uuid.uuid4().hex[:8]}"
    yield robot
    for container in api.containers(all=True, filters={"label": f"io.bridgeos.robot={robot}"}):
        api.remove_container(container["Id"], force=True, v=True)
    for network in api.networks(names=[f"bridgeos-{robot}"]):
        api.remove_network(network["Id"])


def spec(robot: str, component: str, script: str, restart: RestartPolicy | None = None) -> ComponentSpec:
    return ComponentSpec(
        robot=robot,
        skill="cams",
        component=component,
        location="robot",
        launch=LaunchSpec(image=IMAGE, command=["sh", "-c", script]),
        resources=ComponentResources(),
        env={},
        restart=restart or RestartPolicy(),
    )


class NoLink:
    ws = None

    def idle(self, max_buffered: int) -> bool:
        return False


async def test_a_containers_lines_come_with_dockers_time_their_stream_and_level_and_survive_an_agent_restart(
    robot: str, tmp_path: Path
) -> None:
    first = DockerRuntime(robot, data_dir=tmp_path / "runtime")
    service = ComponentLogService(tmp_path / "logs", first, NoLink())  # type: ignore[arg-type]
    task = asyncio.create_task(service.run())
    started = time.time()
    await first.start(spec(robot, "camera", TICKS))
    ring = service.rings.get("cams", "camera")
    assert ring is not None
    await eventually(lambda: ring.seq >= 30, timeout=20, what="30 lines from the container")
    task.cancel()
    await asyncio.gather(task, return_exceptions=True)
    saved = first.get_state()
    await first.close()  # the agent stops; the container keeps printing
    await asyncio.sleep(1)

    second = DockerRuntime(robot, data_dir=tmp_path / "runtime")
    try:
        assert [s.component for s in await second.load_state(saved)] == ["camera"]
        again = ComponentLogService(tmp_path / "logs", second, NoLink())  # type: ignore[arg-type]
        task = asyncio.create_task(again.run())
        ring = again.rings.get("cams", "camera")
        assert ring is not None
        await eventually(lambda: ring.seq >= 150, timeout=20, what="lines after the restart")
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    finally:
        await second.close(stop_components=True)

    lines = ring.lines_after(0, 100_000)
    by_text = {text: (stream, level) for _, _, stream, level, text in lines}
    assert by_text["[INFO] [1.0]: up"] == ("stdout", "info")
    assert by_text["ERROR:cam:no frames"] == ("stderr", "error")
    ticks = [text for *_, text in lines if text.startswith("tick ")]
    assert ticks == [f"tick {i}" for i in range(1, len(ticks) + 1)]  # nothing lost or taken twice over the restart
    assert [line[0] for line in lines] == list(range(1, len(lines) + 1))
    stamps = [ts for _, ts, *_ in lines if ts]
    assert started - 5 < stamps[0] <= stamps[-1] < time.time() + 1  # Docker's times, in order
    assert len(set(stamps)) > len(stamps) // 2  # each line its own time, not the time it was read


async def test_a_crashed_containers_last_lines_are_read_to_its_end(robot: str, tmp_path: Path) -> None:
    runtime = DockerRuntime(robot, data_dir=tmp_path / "runtime")
    service = ComponentLogService(tmp_path / "logs", runtime, NoLink())  # type: ignore[arg-type]
    task = asyncio.create_task(service.run())
    try:
        script = "for i in $(seq 1 60); do echo step $i; done; sleep 0.2; echo 'Traceback: lidar gone' >&2; exit 4"
        await runtime.start(spec(robot, "lidar", script, RestartPolicy(max_restarts=0)))

        async def failed() -> bool:
            return (await runtime.status("cams", "lidar")).status == Status.FAILED

        await eventually(failed, timeout=20, what="the container given up on")
        last = await service.last_lines("cams", "lidar")
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        await runtime.close(stop_components=True)

    assert len(last) == 50
    # In Docker's order: it copies stdout and stderr apart, stamping each line as it gets it (a line
    # printed on stderr within a millisecond of stdout ones may come among them).
    assert last[-1]["text"] == "Traceback: lidar gone" and last[-1]["stream"] == "stderr"
    assert [line["text"] for line in last[:-1]] == [f"step {i}" for i in range(12, 61)]
    assert [line["ts"] for line in last] == sorted(line["ts"] for line in last)
