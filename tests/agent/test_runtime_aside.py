"""A component set aside keeps running beside a new copy under its name (the hand-over), on both runtimes."""

from __future__ import annotations

import asyncio
import dataclasses
import os
import signal
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from docker.api import APIClient

from bridgeos_agent.runtime import ComponentSpec, RuntimeFailure, Status
from bridgeos_agent.runtime.docker import DockerRuntime
from bridgeos_agent.runtime.process import ProcessRuntime
from tests.agent.test_runtime_docker import api, robot
from tests.agent.test_runtime_docker import make_spec as container_spec
from tests.agent.test_runtime_process import FAST, Recorder, alive
from tests.agent.test_runtime_process import make_spec as process_runtime_spec

__all__ = ["api", "robot"]


ROBOT = f"aside-{os.getpid()}"  # control groups of its own, whatever else runs here


def process_spec(*args: Any, **kw: Any) -> ComponentSpec:
    return dataclasses.replace(process_runtime_spec(*args, **kw), robot=ROBOT)


@pytest.fixture
async def processes(tmp_path: Path) -> AsyncIterator[tuple[ProcessRuntime, Recorder]]:
    recorder = Recorder()
    runtime = ProcessRuntime(ROBOT, data_dir=tmp_path, on_status=recorder)
    yield runtime, recorder
    await runtime.close(stop_components=True)


async def test_a_process_set_aside_runs_on_unsupervised_and_unreported_beside_its_new_copy(processes) -> None:
    runtime, recorder = processes
    old = await runtime.start(process_spec("detector", ["sleep", "600"]))
    aside = await runtime.set_aside("people", "detector")
    assert aside is not None
    assert (await runtime.status("people", "detector")).status == Status.ABSENT  # the name is free
    if runtime.cgroups.hierarchy is not None:
        assert aside.group is not None
        # Its control group moved out of the new copy's way, its process with it.
        assert all(d.name.endswith(".aside") and d.exists() for d in aside.group.directories.values())
        assert old.pid_or_container_id in aside.group.members()

    new = await runtime.start(process_spec("detector", ["sleep", "600"]))
    assert new.pid_or_container_id != old.pid_or_container_id
    assert alive(old.pid_or_container_id) and alive(new.pid_or_container_id)
    reported = len(recorder.states)

    await runtime.stop_aside(aside)
    await asyncio.sleep(0.2)
    assert not alive(old.pid_or_container_id) and alive(new.pid_or_container_id)
    assert len(recorder.states) == reported, "the old copy's end is not reported as the component's"
    assert (await runtime.status("people", "detector")).status == Status.RUNNING
    assert [c["component"] for c in runtime.get_state()["components"]] == ["detector"]


async def test_a_process_put_back_is_supervised_again_under_its_name(processes) -> None:
    runtime, _ = processes
    old = await runtime.start(process_spec("detector", ["sleep", "600"], restart=FAST))
    aside = await runtime.set_aside("people", "detector")
    with pytest.raises(RuntimeFailure, match="not found"):
        await runtime.start(process_spec("detector", ["/nonexistent/detector"]))
    await runtime.restore_aside(aside)

    state = await runtime.status("people", "detector")
    assert (state.status, state.pid_or_container_id) == (Status.RUNNING, old.pid_or_container_id)
    if runtime.cgroups.hierarchy is not None:
        # Its control group moved back under its name (over the failed launch's empty one).
        assert aside.group is not None, "the group could not be moved back"
        assert not any(d.name.endswith(".aside") for d in aside.group.directories.values())
        assert old.pid_or_container_id in aside.group.members()
    # Supervised again: killed from outside, it is relaunched.
    os.kill(old.pid_or_container_id, signal.SIGKILL)
    for _ in range(100):
        state = await runtime.status("people", "detector")
        if state.restarts == 1 and state.status == Status.RUNNING:
            break
        await asyncio.sleep(0.05)
    assert state.restarts == 1 and state.status == Status.RUNNING


@pytest.mark.docker
async def test_a_container_set_aside_gives_its_name_to_the_new_copy_and_is_removed_at_its_stop(
    api: APIClient, robot: str, tmp_path: Path
) -> None:
    runtime = DockerRuntime(robot, data_dir=tmp_path)
    try:
        old = await runtime.start(container_spec(robot, "detector"))
        aside = await runtime.set_aside("people", "detector")
        name = runtime.container_name("people", "detector")
        assert api.inspect_container(old.pid_or_container_id)["Name"] == f"/{name}-aside"

        new = await runtime.start(container_spec(robot, "detector"))
        assert api.inspect_container(new.pid_or_container_id)["Name"] == f"/{name}"
        running = {c["Id"] for c in api.containers(filters={"label": f"io.bridgeos.robot={robot}"})}
        assert {old.pid_or_container_id, new.pid_or_container_id} <= running

        await runtime.stop_aside(aside)
        running = {c["Id"] for c in api.containers(all=True, filters={"label": f"io.bridgeos.robot={robot}"})}
        assert old.pid_or_container_id not in running and new.pid_or_container_id in running
        assert (await runtime.status("people", "detector")).status == Status.RUNNING

        # Put back: the new copy stopped first frees the name.
        again = await runtime.set_aside("people", "detector")
        await runtime.stop("people", "detector")
        await runtime.restore_aside(again)
        assert api.inspect_container(new.pid_or_container_id)["Name"] == f"/{name}"
        assert (await runtime.status("people", "detector")).status == Status.RUNNING
    finally:
        await runtime.close(stop_components=True)
