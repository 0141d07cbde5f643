"""Test the process runtime against real processes: launch, supervise, stop, re-adopt."""

from __future__ import annotations

import asyncio
import gc
import itertools
import json
import os
import shlex
import signal
import sys
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import psutil
import pytest

from bridgeos_agent.runtime import (
    ComponentSpec,
    ComponentState,
    ProcessRuntime,
    RestartPolicy,
    RuntimeFailure,
    Status,
    create_runtime,
    usage,
)
from bridgeos_agent.runtime.base import RestartBudget
from bridgeos_agent.skillconfig import ComponentResources, LaunchSpec
from tests.conftest import eventually

ROBOT = "robot-1"
FAST = RestartPolicy(max_restarts=3, window=60.0, backoff_initial=0.05, backoff_max=1.0, jitter=0.0)
CONTRACT = {
    "BRIDGEOS_MANAGER_URL": "http://127.0.0.1:9100/skills/people",
    "BRIDGEOS_SKILL": "people",
    "BRIDGEOS_COMPONENT": "detector",
    "BRIDGEOS_LOCATION": "robot",
    "ROS_MASTER_URI": "http://127.0.0.1:11311",
    "ROS_NAMESPACE": "/people/detector",
}
# A runtime closed without stopping leaves its children to the next one on purpose.
LEFT_RUNNING = pytest.mark.filterwarnings("ignore:subprocess .* is still running:ResourceWarning")


def collect_handles() -> None:
    """Free a closed runtime's process handles now, so their warnings land in this test."""
    gc.collect()


def make_spec(
    component: str,
    command: list[str] | str | None,
    *,
    skill: str = "people",
    env: dict[str, str] | None = None,
    launch_env: dict[str, str] | None = None,
    restart: RestartPolicy = FAST,
    volumes: tuple[str, ...] = (),
    image: str | None = None,
    resources: ComponentResources | None = None,
) -> ComponentSpec:
    """Build a component spec the way the controller would."""
    return ComponentSpec(
        robot=ROBOT,
        skill=skill,
        component=component,
        location="robot",
        launch=LaunchSpec(command=command, image=image, env=launch_env or {}),
        resources=resources or ComponentResources(cpu=0.1, ram=32),
        env=env if env is not None else {"BRIDGEOS_SKILL": skill, "BRIDGEOS_COMPONENT": component},
        volumes=volumes,
        restart=restart,
    )


def python(code: str) -> list[str]:
    """Return a command running Python code with the test's interpreter."""
    return [sys.executable, "-c", code]


SLEEP = ["sleep", "3600"]


def alive(pid: int) -> bool:
    """Say whether a process exists and is not a zombie."""
    try:
        return psutil.Process(pid).status() != psutil.STATUS_ZOMBIE
    except psutil.NoSuchProcess:
        return False


class Recorder:
    """Collect every status change a runtime reports."""

    def __init__(self) -> None:
        self.states: list[ComponentState] = []

    def __call__(self, state: ComponentState) -> None:
        self.states.append(state)

    def statuses(self, component: str) -> list[str]:
        return [str(s.status) for s in self.states if s.component == component]


@pytest.fixture
def recorder() -> Recorder:
    return Recorder()


@pytest.fixture
async def runtime(tmp_path: Path, recorder: Recorder) -> AsyncIterator[ProcessRuntime]:
    runtime = ProcessRuntime(ROBOT, data_dir=tmp_path, on_status=recorder)
    yield runtime
    await runtime.close(stop_components=True)


async def test_start_runs_the_command_and_reports_running(runtime: ProcessRuntime, recorder: Recorder) -> None:
    state = await runtime.start(make_spec("detector", SLEEP))

    assert state.status == Status.RUNNING
    assert isinstance(state.pid_or_container_id, int) and alive(state.pid_or_container_id)
    assert state.started_at == pytest.approx(time.time(), abs=5)
    assert (await runtime.status("people", "detector")) == state
    assert recorder.statuses("detector") == ["starting", "running"]


async def test_component_sees_the_env_contract_its_volumes_and_its_own_directory(
    runtime: ProcessRuntime, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("BRIDGEOS_TOKEN", "secret-of-the-agent")
    dump = (
        "import json, os, pathlib, time; "
        "pathlib.Path('env.json').write_text(json.dumps({'env': dict(os.environ), 'cwd': os.getcwd()})); "
        "time.sleep(3600)"
    )
    spec = make_spec(
        "detector",
        python(dump),
        env=CONTRACT,
        launch_env={"MODEL": "yolo", "BRIDGEOS_LOCATION": "overridden by the contract"},
        volumes=("maps",),
    )
    await runtime.start(spec)

    written = runtime.work_dir("people", "detector") / "env.json"
    seen = json.loads(await eventually(lambda: written.exists() and written.read_text(), timeout=10, what="env.json"))
    env = seen["env"]
    assert {k: env.get(k) for k in CONTRACT} == CONTRACT
    assert env["MODEL"] == "yolo"
    # The agent's PATH, then its own scripts' directory (bridgeos-usecase) unless already on it.
    scripts = os.path.dirname(sys.executable)
    expected = (
        os.environ["PATH"] if scripts in os.environ["PATH"].split(os.pathsep) else f"{os.environ['PATH']}:{scripts}"
    )
    assert env["PATH"] == expected
    assert "BRIDGEOS_TOKEN" not in env
    assert Path(seen["cwd"]) == runtime.work_dir("people", "detector")
    assert Path(env["BRIDGEOS_VOLUMES"]) == tmp_path / "volumes" / "people"
    assert (Path(env["BRIDGEOS_VOLUMES"]) / "maps").is_dir()


async def test_logs_return_the_last_lines_of_stdout_and_stderr(runtime: ProcessRuntime) -> None:
    code = "import sys, time\nfor i in range(1, 301): print(i)\nprint('oops', file=sys.stderr)\ntime.sleep(3600)"
    await runtime.start(make_spec("detector", python(code)))

    await eventually(lambda: _ends_with(runtime, "oops"), timeout=10, what="stderr in the log")

    assert await runtime.logs("people", "detector", tail=4) == ["298", "299", "300", "oops"]
    assert len(await runtime.logs("people", "detector", tail=1000)) == 301


async def _ends_with(runtime: ProcessRuntime, line: str) -> bool:
    return (await runtime.logs("people", "detector", tail=1)) == [line]


async def test_stop_terminates_and_is_not_taken_for_a_crash(runtime: ProcessRuntime, recorder: Recorder) -> None:
    state = await runtime.start(make_spec("detector", SLEEP))

    stopped = await runtime.stop("people", "detector")

    assert stopped.status == Status.STOPPED
    assert stopped.exit_code == 128 + signal.SIGTERM
    assert not alive(state.pid_or_container_id)
    await asyncio.sleep(0.3)  # longer than the backoff: a restart would have happened
    assert (await runtime.status("people", "detector")).status == Status.STOPPED
    assert recorder.statuses("detector") == ["starting", "running", "stopped"]


async def test_stop_kills_the_whole_process_group(runtime: ProcessRuntime) -> None:
    await runtime.start(make_spec("detector", ["sh", "-c", "sleep 3600 & echo $! > child.pid; wait"]))
    child_file = runtime.work_dir("people", "detector") / "child.pid"
    child = int(
        await eventually(lambda: child_file.exists() and child_file.read_text().strip(), timeout=10, what="child.pid")
    )
    assert alive(child)

    await runtime.stop("people", "detector")

    await eventually(lambda: not alive(child), timeout=2, what="the child to die")


async def test_stop_kills_a_group_ignoring_sigterm_once_the_timeout_passes(runtime: ProcessRuntime) -> None:
    # An ignored signal stays ignored across exec, so the child sleep ignores SIGTERM too.
    command = ["sh", "-c", "trap '' TERM; sleep 3600 & echo $! > child.pid; while :; do sleep 0.1; done"]
    state = await runtime.start(make_spec("detector", command))
    child_file = runtime.work_dir("people", "detector") / "child.pid"
    child = int(
        await eventually(lambda: child_file.exists() and child_file.read_text().strip(), timeout=10, what="child.pid")
    )

    began = time.monotonic()
    stopped = await runtime.stop("people", "detector", timeout=0.5)

    assert 0.5 <= time.monotonic() - began < 3
    assert stopped.exit_code == 128 + signal.SIGKILL
    assert not alive(state.pid_or_container_id)
    await eventually(lambda: not alive(child), timeout=2, what="the child to die")


async def test_crash_restarts_with_growing_backoff_then_gives_up(runtime: ProcessRuntime, recorder: Recorder) -> None:
    await runtime.start(make_spec("detector", ["sh", "-c", "echo crashing; exit 3"]))

    final = await eventually(_status_is(runtime, "detector", Status.FAILED), timeout=10, what="failed")
    assert final.restarts == 3
    assert final.exit_code == 3
    assert "crashed 4 times within 60 s (last exit code 3)" in final.message
    assert recorder.statuses("detector") == ["starting", "running"] + ["restarting", "running"] * 3 + ["failed"]
    relaunches = [s.started_at for s in recorder.states if s.status == Status.RUNNING]
    gaps = [later - earlier for earlier, later in itertools.pairwise(relaunches)]
    assert len(gaps) == 3
    assert gaps[0] >= 0.05 and gaps[1] >= 0.1 and gaps[2] >= 0.2
    assert await runtime.logs("people", "detector") == ["crashing"] * 4


def _status_is(runtime: ProcessRuntime, component: str, status: Status) -> Callable[[], Any]:
    async def check() -> ComponentState | None:
        state = await runtime.status("people", component)
        return state if state.status == status else None

    return check


async def test_clean_exit_is_not_restarted(runtime: ProcessRuntime, recorder: Recorder) -> None:
    await runtime.start(make_spec("detector", ["true"]))

    final = await eventually(_status_is(runtime, "detector", Status.EXITED), timeout=10, what="exited")

    assert final.exit_code == 0 and final.restarts == 0
    await asyncio.sleep(0.2)
    assert recorder.statuses("detector") == ["starting", "running", "exited"]


async def test_a_component_killed_from_outside_is_restarted(runtime: ProcessRuntime) -> None:
    first = await runtime.start(make_spec("detector", SLEEP))

    os.kill(first.pid_or_container_id, signal.SIGKILL)

    again = await eventually(
        lambda: _restarted(runtime, "detector"),
        timeout=10,
        what="a restart",
    )
    assert again.pid_or_container_id != first.pid_or_container_id
    assert alive(again.pid_or_container_id)


async def _restarted(runtime: ProcessRuntime, component: str) -> ComponentState | None:
    state = await runtime.status("people", component)
    return state if state.status == Status.RUNNING and state.restarts >= 1 else None


async def test_stop_during_the_backoff_cancels_the_restart(runtime: ProcessRuntime, recorder: Recorder) -> None:
    slow = RestartPolicy(max_restarts=3, backoff_initial=0.5, jitter=0.0)
    await runtime.start(make_spec("detector", ["false"], restart=slow))
    await eventually(_status_is(runtime, "detector", Status.RESTARTING), timeout=10, what="restarting")

    stopped = await runtime.stop("people", "detector")

    assert stopped.status == Status.STOPPED
    await asyncio.sleep(0.7)
    assert recorder.statuses("detector") == ["starting", "running", "restarting", "stopped"]


def test_restart_budget_backs_off_then_forgets_old_crashes() -> None:
    budget = RestartBudget(RestartPolicy(max_restarts=3, window=10.0, backoff_initial=0.5, backoff_max=1.5, jitter=0))

    assert [budget.next_delay(t) for t in (0.0, 1.0, 2.0, 3.0)] == [0.5, 1.0, 1.5, None]
    assert budget.next_delay(10.5) == 1.5  # two crashes still in the window
    assert budget.next_delay(25.0) == 0.5  # a long quiet run resets the backoff


def test_restart_delay_jitter_stays_within_its_fraction() -> None:
    policy = RestartPolicy(backoff_initial=1.0, backoff_max=30.0, jitter=0.1)

    delays = [policy.delay(3) for _ in range(200)]

    assert all(7.2 <= d <= 8.8 for d in delays)
    assert len(set(delays)) > 1
    assert policy.delay(40) <= 33.0


async def test_start_is_idempotent(runtime: ProcessRuntime) -> None:
    first = await runtime.start(make_spec("detector", SLEEP))

    second = await runtime.start(make_spec("detector", SLEEP))

    assert second == first
    sessions = [p for p in psutil.process_iter(["pid"]) if _session(p.pid) == first.pid_or_container_id]
    assert [p.pid for p in sessions] == [first.pid_or_container_id]


def _session(pid: int) -> int | None:
    try:
        return os.getsid(pid)
    except OSError:
        return None


async def test_start_after_stop_launches_again(runtime: ProcessRuntime) -> None:
    first = await runtime.start(make_spec("detector", SLEEP))
    await runtime.stop("people", "detector")

    second = await runtime.start(make_spec("detector", SLEEP))

    assert second.status == Status.RUNNING
    assert second.pid_or_container_id != first.pid_or_container_id


async def test_missing_command_is_a_clear_failure(runtime: ProcessRuntime, recorder: Recorder) -> None:
    with pytest.raises(RuntimeFailure, match=r"command '/opt/nowhere/detector' not found.*install it"):
        await runtime.start(make_spec("detector", ["/opt/nowhere/detector", "--fast"]))

    failed = await runtime.status("people", "detector")
    assert failed.status == Status.FAILED
    assert "not found" in failed.message
    assert recorder.statuses("detector") == ["starting", "failed"]
    assert "not found" in (await runtime.logs("people", "detector"))[-1]


async def test_image_only_launch_spec_says_to_add_a_command(runtime: ProcessRuntime) -> None:
    with pytest.raises(RuntimeFailure, match=r"no command for the process runtime.*--runtime docker"):
        await runtime.start(make_spec("detector", None, image="bridgeos/base:bookworm"))


async def test_unknown_component_is_absent_without_error(runtime: ProcessRuntime) -> None:
    assert (await runtime.stop("people", "ghost")).status == Status.ABSENT
    assert (await runtime.status("people", "ghost")).status == Status.ABSENT
    assert await runtime.logs("people", "ghost") == []


async def test_ids_that_are_not_slugs_are_refused(runtime: ProcessRuntime) -> None:
    with pytest.raises(ValueError, match="invalid skill id"):
        await runtime.start(make_spec("detector", SLEEP, skill="../etc"))
    with pytest.raises(ValueError, match="invalid component id"):
        await runtime.logs("people", "../../passwd")
    with pytest.raises(ValueError, match="invalid volume name"):
        await runtime.start(make_spec("detector", SLEEP, volumes=("maps/../../etc",)))


async def test_stats_sum_cpu_and_memory_over_the_process_tree(runtime: ProcessRuntime) -> None:
    hog = python("x = bytearray(64 * 2**20)\nimport time\ntime.sleep(3600)")
    busy = python("while True: pass")
    # Declared above what they use: the runtime enforces declared resources (runtime/cgroups.py).
    roomy = ComponentResources(cpu=1.0, ram=128)
    await runtime.start(make_spec("memory", ["sh", "-c", f"{shlex.join(hog)} & wait"], resources=roomy))
    await runtime.start(make_spec("busy", busy, resources=roomy))
    await runtime.start(make_spec("idle", SLEEP))
    await runtime.stats()
    # CPU is a rate over the time between two samples; on a loaded machine the busy loop may get
    # only a small share of a core in any one second, so sample until it shows (or give up).
    deadline = time.monotonic() + 30
    while True:
        await asyncio.sleep(1.0)
        usage = await runtime.stats()
        if usage[("people", "busy")].cpu > 0.1 and usage[("people", "memory")].ram >= 64:
            break
        if time.monotonic() > deadline:
            break

    assert set(usage) == {("people", "memory"), ("people", "busy"), ("people", "idle")}
    assert usage[("people", "memory")].ram >= 64  # the shell's child holds the memory
    assert usage[("people", "idle")].ram < 16
    assert usage[("people", "busy")].cpu > 0.1
    assert usage[("people", "idle")].cpu < 0.05
    assert all(u.net_rx == 0 and u.io_read >= 0 for u in usage.values())


@LEFT_RUNNING
@pytest.mark.parametrize("use_pidfd", [True, False], ids=["pidfd", "polling"])
async def test_a_new_runtime_readopts_running_components_and_forgets_dead_ones(tmp_path: Path, use_pidfd: bool) -> None:
    first = ProcessRuntime(ROBOT, data_dir=tmp_path, use_pidfd=use_pidfd, poll_interval=0.05)
    kept = await first.start(make_spec("detector", ["sh", "-c", "sleep 3600 & echo $! > child.pid; wait"]))
    dead = await first.start(make_spec("sampler", SLEEP))
    child_file = first.work_dir("people", "detector") / "child.pid"
    child = int(
        await eventually(lambda: child_file.exists() and child_file.read_text().strip(), timeout=10, what="child.pid")
    )
    saved = json.loads(json.dumps(first.get_state()))
    await first.close()
    collect_handles()
    assert alive(kept.pid_or_container_id)
    os.kill(dead.pid_or_container_id, signal.SIGKILL)
    await eventually(lambda: not alive(dead.pid_or_container_id), timeout=10, what="the sampler to die")

    recorder = Recorder()
    second = ProcessRuntime(ROBOT, data_dir=tmp_path, on_status=recorder, use_pidfd=use_pidfd, poll_interval=0.05)
    try:
        adopted = await second.load_state(saved)

        assert [(s.component, s.pid_or_container_id, s.status) for s in adopted] == [
            ("detector", kept.pid_or_container_id, Status.RUNNING)
        ]
        assert (await second.status("people", "sampler")).status == Status.ABSENT
        assert "pid" in json.dumps(second.get_state())

        # An adopted component that crashes is restarted from its saved spec.
        os.kill(kept.pid_or_container_id, signal.SIGKILL)
        again = await eventually(lambda: _restarted(second, "detector"), timeout=10, what="a restart")
        assert again.pid_or_container_id != kept.pid_or_container_id
        assert recorder.statuses("detector")[:2] == ["restarting", "running"]

        await second.stop("people", "detector")
        assert not alive(again.pid_or_container_id)
        await eventually(lambda: not alive(child), timeout=10, what="the first launch's child to die")
    finally:
        await second.close(stop_components=True)


@LEFT_RUNNING
async def test_adopted_component_is_stopped_with_its_group(tmp_path: Path) -> None:
    first = ProcessRuntime(ROBOT, data_dir=tmp_path)
    state = await first.start(make_spec("detector", ["sh", "-c", "sleep 3600 & echo $! > child.pid; wait"]))
    child_file = first.work_dir("people", "detector") / "child.pid"
    child = int(
        await eventually(lambda: child_file.exists() and child_file.read_text().strip(), timeout=10, what="child.pid")
    )
    saved = first.get_state()
    await first.close()
    collect_handles()

    second = ProcessRuntime(ROBOT, data_dir=tmp_path)
    try:
        await second.load_state(saved)
        stopped = await second.stop("people", "detector")
    finally:
        await second.close(stop_components=True)

    assert stopped.status == Status.STOPPED
    await eventually(
        lambda: not alive(state.pid_or_container_id) and not alive(child), timeout=10, what="the group to die"
    )


async def test_load_state_ignores_a_pid_now_used_by_another_process(runtime: ProcessRuntime) -> None:
    spec = make_spec("detector", SLEEP)
    saved = {
        "runtime": "process",
        "components": [
            {
                "skill": "people",
                "component": "detector",
                "pid": os.getpid(),
                "create_time": 1.0,
                "spec": spec.to_dict(),
            },
            {"skill": "people", "component": "broken", "pid": "not a pid"},
        ],
    }

    assert await runtime.load_state(saved) == []
    assert (await runtime.status("people", "detector")).status == Status.ABSENT


async def test_close_can_stop_every_component(tmp_path: Path) -> None:
    runtime = create_runtime("process", ROBOT, data_dir=tmp_path)
    states = [await runtime.start(make_spec(f"c{i}", SLEEP)) for i in range(3)]

    await runtime.close(stop_components=True)

    assert not any(alive(s.pid_or_container_id) for s in states)


async def test_a_big_log_is_rotated_while_the_component_runs(tmp_path: Path) -> None:
    runtime = ProcessRuntime(ROBOT, data_dir=tmp_path, log_max_bytes=2000, log_check_interval=0.05)
    try:
        code = "import time\nfor i in range(1000): print(f'line {i:04d}')\ntime.sleep(0.3)\nprint('after')\ntime.sleep(3600)"
        await runtime.start(make_spec("detector", python(code)))
        log = runtime.log_path("people", "detector")
        await eventually(lambda: log.with_name(log.name + ".1").exists(), timeout=10, what="the rotated log")
        await eventually(lambda: _ends_with(runtime, "after"), timeout=10, what="a line after the rotation")

        assert log.stat().st_size < 2000
        assert (await runtime.logs("people", "detector", tail=2))[-1] == "after"
    finally:
        await runtime.close(stop_components=True)


async def test_a_crashed_components_leftover_children_die_before_the_relaunch(runtime: ProcessRuntime) -> None:
    command = ["sh", "-c", "sleep 3600 & echo $! >> children; sleep 0.2; exit 1"]
    await runtime.start(make_spec("detector", command, restart=RestartPolicy(max_restarts=1, jitter=0)))
    children = runtime.work_dir("people", "detector") / "children"

    await eventually(_status_is(runtime, "detector", Status.FAILED), timeout=10, what="failed")

    pids = [int(line) for line in children.read_text().split()]
    assert len(pids) == 2
    await eventually(lambda: not any(alive(pid) for pid in pids), timeout=2, what="the orphans to die")


async def test_a_command_the_shell_cannot_find_fails_without_restarts(runtime: ProcessRuntime) -> None:
    await runtime.start(make_spec("detector", ["sh", "-c", "exec /opt/nowhere/detector"]))

    final = await eventually(_status_is(runtime, "detector", Status.FAILED), timeout=10, what="failed")

    assert final.exit_code == 127 and final.restarts == 0
    assert "was not found (exit 127)" in final.message


@pytest.mark.parametrize("children_lists", [True, False], ids=["proc-children", "process-table"])
def test_a_component_s_measure_sums_its_whole_process_tree(monkeypatch, children_lists):
    # A grandchild burns the CPU: found through /proc's children lists, or the process table without them.
    monkeypatch.setattr(usage, "_PROC_CHILDREN", children_lists and usage._PROC_CHILDREN)
    burn = "import time\nend = time.process_time() + 0.3\nwhile time.process_time() < end: pass\ntime.sleep(60)"
    root = psutil.Popen(["sh", "-c", f"sh -c {shlex.quote(shlex.join([sys.executable, '-c', burn]))} & wait"])
    try:
        deadline = time.monotonic() + 30
        while True:
            measured, _ = usage.measure([(("people", "detector"), root.pid, {})])[("people", "detector")]
            if measured.cpu >= 0.3 or time.monotonic() > deadline:
                break
            time.sleep(0.1)
        assert measured.cpu >= 0.3
        assert measured.ram > 5  # the interpreter's RSS, two levels down
        assert usage.measure([(("people", "gone"), 2**22 + 7, {})])[("people", "gone")][0].cpu == 0
    finally:
        for process in [*root.children(recursive=True), root]:
            process.kill()
        root.wait()
