"""The process runtime holds components to their resources with real cgroups and real processes."""

from __future__ import annotations

import asyncio
import logging
import os
import sys
import time
from pathlib import Path

import psutil
import pytest

from bridgeos_agent.runtime import ComponentSpec, ProcessRuntime, RestartPolicy, Status
from bridgeos_agent.runtime.cgroups import (
    CPU_PERIOD_US,
    MIB,
    MIN_MEMORY,
    Cgroups,
    Hierarchy,
    cpu_quota_us,
    find_hierarchy,
    limits_for,
    memory_limit_bytes,
)
from bridgeos_agent.skillconfig import ComponentResources, LaunchSpec

ROBOT = "cg-robot"
FAST = RestartPolicy(max_restarts=5, window=60.0, backoff_initial=0.1, backoff_max=0.5, jitter=0.0)
CGROUPS = Cgroups(ROBOT)
needs_cgroups = pytest.mark.skipif(
    CGROUPS.hierarchy is None, reason=f"component limits: {CGROUPS.describe()} (needs root and cgroups)"
)

# Three busy processes: all the CPU a 2-core robot has, and more.
SPIN = """
import os
for _ in range(2):
    if os.fork() == 0:
        break
while True:
    pass
"""
# Grows by 10 MiB every 50 ms; stops at 400 MiB so a machine without limits is not hurt.
EAT = """
import time
blocks = []
while len(blocks) < 40:
    blocks.append(bytearray(10 * 1024 * 1024))
    time.sleep(0.05)
print("ate 400 MiB and was not stopped", flush=True)
time.sleep(3600)
"""


def spec(component: str, code: str, *, cpu: float = 0.0, ram: float = 0.0) -> ComponentSpec:
    """Build a component running Python code with the given limits."""
    return ComponentSpec(
        robot=ROBOT,
        skill="limits",
        component=component,
        location="robot",
        launch=LaunchSpec(command=[sys.executable, "-c", code]),
        resources=ComponentResources(cpu=cpu, ram=ram),
        env={},
        restart=FAST,
    )


def tree_cpu_seconds(pid: int) -> float:
    """Return the CPU time a process and its children used so far."""
    total = 0.0
    for proc in [psutil.Process(pid), *psutil.Process(pid).children(recursive=True)]:
        try:
            times = proc.cpu_times()
        except psutil.Error:
            continue
        total += times.user + times.system
    return total


# --------------------------------------------------------------------------- pure arithmetic


def test_cores_become_a_quota_per_period() -> None:
    assert cpu_quota_us(0.5, cpus=2) == CPU_PERIOD_US // 2
    assert cpu_quota_us(1.5, cpus=2) == 150_000


def test_no_cpu_declared_means_no_cpu_limit() -> None:
    assert cpu_quota_us(0.0, cpus=2) is None


def test_more_cores_than_the_robot_has_is_capped_and_tiny_quotas_are_raised() -> None:
    assert cpu_quota_us(30.0, cpus=2) == 2 * CPU_PERIOD_US
    assert cpu_quota_us(0.0001, cpus=2) == 1_000


def test_mebibytes_become_a_memory_ceiling() -> None:
    assert memory_limit_bytes(100) == 100 * MIB
    assert memory_limit_bytes(0) is None
    assert memory_limit_bytes(1) == MIN_MEMORY


def test_limits_follow_the_declared_resources() -> None:
    limits = limits_for(ComponentResources(cpu=0.5, ram=100), cpus=4)
    assert (limits.cpu_quota_us, limits.memory_bytes, limits.any) == (50_000, 100 * MIB, True)
    assert not limits_for(ComponentResources(), cpus=4).any


MOUNTS_V1 = """sysfs /sys sysfs rw 0 0
cgroup /sys/fs/cgroup/cpu,cpuacct cgroup rw,relatime,cpu,cpuacct 0 0
cgroup /sys/fs/cgroup/memory cgroup rw,relatime,memory 0 0
cgroup2 /sys/fs/cgroup/unified cgroup2 rw,relatime 0 0
"""
OWN_V1 = "5:memory:/agents/a1\n2:cpu,cpuacct:/\n0::/\n"


def test_cgroup_v1_groups_hang_from_the_agents_own_groups() -> None:
    found = find_hierarchy(MOUNTS_V1, OWN_V1, v2_controllers=lambda _: "hugetlb")
    assert found == Hierarchy(
        "v1", {"cpu": Path("/sys/fs/cgroup/cpu,cpuacct"), "memory": Path("/sys/fs/cgroup/memory/agents/a1")}
    )


def test_cgroup_v2_is_preferred_when_it_has_cpu_and_memory() -> None:
    mounts = "cgroup2 /sys/fs/cgroup cgroup2 rw 0 0\n"
    found = find_hierarchy(mounts, "0::/system.slice/agent.service\n", v2_controllers=lambda _: "cpuset cpu io memory")
    assert found == Hierarchy("v2", {"": Path("/sys/fs/cgroup")})
    assert find_hierarchy(mounts, "0::/\n", v2_controllers=lambda _: "cpu io") is None


def test_without_cgroups_a_limited_component_runs_and_the_agent_says_limits_are_not_enforced(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    async def scenario() -> None:
        runtime = ProcessRuntime(ROBOT, data_dir=tmp_path, cgroups=Cgroups(ROBOT, hierarchy=None))
        try:
            for name in ("a", "b"):
                state = await runtime.start(spec(name, "import time; time.sleep(60)", cpu=0.5, ram=64))
                assert state.status is Status.RUNNING
        finally:
            await runtime.close(stop_components=True)

    with caplog.at_level(logging.WARNING, logger="bridgeos_agent"):
        asyncio.run(scenario())
    said = [r.getMessage() for r in caplog.records if "NOT enforced" in r.getMessage()]
    assert len(said) == 1, said  # once, not once per component


# --------------------------------------------------------------------------- real cgroups


@needs_cgroups
def test_a_component_that_spins_on_every_core_gets_its_cpu_limit_only(tmp_path: Path) -> None:
    async def scenario() -> float:
        runtime = ProcessRuntime(ROBOT, data_dir=tmp_path, cgroups=Cgroups(ROBOT))
        try:
            state = await runtime.start(spec("spinner", SPIN, cpu=0.5))
            pid = int(state.pid_or_container_id or 0)
            await asyncio.sleep(0.5)  # its children have forked
            group = runtime._records[("limits", "spinner")].group
            assert group is not None
            # Every process it forked is inside its group, none escaped.
            assert {p.pid for p in psutil.Process(pid).children(recursive=True)} <= group.members()
            assert len(group.members()) == 3
            before, started = tree_cpu_seconds(pid), time.monotonic()
            await asyncio.sleep(2.0)
            return (tree_cpu_seconds(pid) - before) / (time.monotonic() - started)
        finally:
            await runtime.close(stop_components=True)

    cores = asyncio.run(scenario())
    # Three spinning processes would take both cores; the quota holds them to half of one.
    # (Under it on a busy machine: the upper bound is the limit, the lower one says it ran at all.)
    assert 0.05 < cores < 0.6, cores


@needs_cgroups
def test_a_component_over_its_memory_is_killed_restarted_and_reported(tmp_path: Path) -> None:
    statuses: list[tuple[Status, str | None]] = []

    async def scenario() -> None:
        runtime = ProcessRuntime(
            ROBOT, data_dir=tmp_path, cgroups=Cgroups(ROBOT), on_status=lambda s: statuses.append((s.status, s.message))
        )
        try:
            await runtime.start(spec("eater", EAT, ram=100))
            group = runtime._records[("limits", "eater")].group
            assert group is not None
            assert (group.directories["memory"] / "memory.limit_in_bytes").read_text().strip() == str(100 * MIB)
            deadline = time.monotonic() + 15
            while (await runtime.status("limits", "eater")).restarts < 1:
                assert time.monotonic() < deadline, "the eater was not killed and restarted"
                await asyncio.sleep(0.05)
            assert (await runtime.status("limits", "eater")).status is Status.RUNNING
            assert "ate 400 MiB" not in "".join(await runtime.logs("limits", "eater"))
        finally:
            await runtime.close(stop_components=True)

    asyncio.run(scenario())
    restarting = [message for status, message in statuses if status is Status.RESTARTING]
    assert restarting and "memory limit of 100 MiB" in (restarting[0] or ""), statuses


@needs_cgroups
def test_stopping_a_component_removes_its_group(tmp_path: Path) -> None:
    async def scenario() -> list[Path]:
        runtime = ProcessRuntime(ROBOT, data_dir=tmp_path, cgroups=Cgroups(ROBOT))
        try:
            await runtime.start(spec("sleeper", "import time; time.sleep(60)", cpu=0.2, ram=50))
            group = runtime._records[("limits", "sleeper")].group
            assert group is not None
            directories = list(group.directories.values())
            assert all(d.is_dir() for d in directories)
            if "cpu" in group.directories:
                assert (group.directories["cpu"] / "cpu.cfs_quota_us").read_text().strip() == "20000"
            await runtime.stop("limits", "sleeper", timeout=2)
            return directories
        finally:
            await runtime.close(stop_components=True)

    directories = asyncio.run(scenario())
    assert not any(d.exists() for d in directories)


@needs_cgroups
def test_a_component_that_ends_for_good_leaves_no_group_and_a_new_runtime_sweeps_empty_ones(tmp_path: Path) -> None:
    async def scenario() -> None:
        runtime = ProcessRuntime(ROBOT, data_dir=tmp_path, cgroups=Cgroups(ROBOT))
        try:
            await runtime.start(spec("done", "print('bye')", cpu=0.2))
            group = runtime._records[("limits", "done")].group
            assert group is not None
            deadline = time.monotonic() + 10
            while (await runtime.status("limits", "done")).status is not Status.EXITED:
                assert time.monotonic() < deadline
                await asyncio.sleep(0.02)
            await asyncio.sleep(0.2)
            assert not any(d.exists() for d in group.directories.values())
            # A group left behind (its component killed while no agent watched) next to a running one.
            await runtime.start(spec("runner", "import time; time.sleep(60)", cpu=0.2))
            running = runtime._records[("limits", "runner")].group
            assert running is not None
            left = Cgroups(ROBOT).group(spec("gone", "", cpu=0.2))
            assert left is not None
            left.create()
            assert Cgroups(ROBOT).sweep() == 0, "a group younger than a minute may be a launch in progress"
            for directory in left.directories.values():
                os.utime(directory, (time.time() - 120, time.time() - 120))
            assert Cgroups(ROBOT).sweep() == len(left.directories)
            assert not any(d.exists() for d in left.directories.values())
            assert all(d.exists() for d in running.directories.values())
        finally:
            await runtime.close(stop_components=True)

    asyncio.run(scenario())
