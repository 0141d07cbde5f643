"""Measure what components consume: Docker stats samples and local process trees.

One place for the measuring the robot's runtimes and the cloud's runtimes (Docker, Swarm,
process) share, so each backend only says where its samples come from.
"""

from __future__ import annotations

import asyncio
import json
import os
import time
from collections import defaultdict
from collections.abc import Callable, Mapping
from typing import Any

import psutil

from bridgeos_agent.runtime.base import RestartPolicy, RuntimeFailure, Usage

__all__ = ["MIB", "CpuSeen", "cpu_share", "docker_usage", "get_json", "measure", "policy_from_label", "sample_stats"]

MIB = 1024 * 1024

# CPU seconds seen per (pid, create_time) of a process tree at the previous measurement.
CpuSeen = dict[tuple[int, float], float]


async def get_json(socket_path: str, url: str, timeout: float = 10.0) -> Any:
    """GET a Docker API URL over its unix socket; HTTP/1.0, so the answer simply ends at EOF."""
    async with asyncio.timeout(timeout):
        reader, writer = await asyncio.open_unix_connection(socket_path)
        try:
            writer.write(f"GET {url} HTTP/1.0\r\nHost: docker\r\n\r\n".encode())
            data = await reader.read()
        finally:
            writer.close()
    head, _, body = data.partition(b"\r\n\r\n")
    status = head.split(b"\r\n", 1)[0].decode("latin-1")
    if status.split(" ")[1:2] != ["200"]:
        raise RuntimeFailure(f"Docker answered {status!r} to GET {url}")
    return json.loads(body)


def docker_usage(raw: Mapping[str, Any]) -> tuple[Usage, float]:
    """Turn a Docker stats sample into usage and the container's total CPU seconds."""
    cpu_seconds = ((raw.get("cpu_stats") or {}).get("cpu_usage") or {}).get("total_usage", 0) / 1e9
    memory = raw.get("memory_stats") or {}
    detail = memory.get("stats") or {}
    # What `docker stats` shows: usage minus the page cache the kernel can drop.
    cache = detail.get("inactive_file", detail.get("total_inactive_file", detail.get("cache", 0)))
    ram = max(memory.get("usage", 0) - cache, 0) / MIB
    networks = (raw.get("networks") or {}).values()
    io_read = io_write = 0
    for entry in (raw.get("blkio_stats") or {}).get("io_service_bytes_recursive") or ():
        op = str(entry.get("op", "")).lower()
        if op == "read":
            io_read += entry.get("value", 0)
        elif op == "write":
            io_write += entry.get("value", 0)
    usage = Usage(
        ram=ram,
        net_rx=sum(n.get("rx_bytes", 0) for n in networks),
        net_tx=sum(n.get("tx_bytes", 0) for n in networks),
        io_read=io_read,
        io_write=io_write,
    )
    return usage, cpu_seconds


def cpu_share(raw: Mapping[str, Any]) -> float:
    """Return cores used between Docker's two stats samples."""
    cpu = raw.get("cpu_stats") or {}
    pre = raw.get("precpu_stats") or {}
    used = ((cpu.get("cpu_usage") or {}).get("total_usage", 0)) - ((pre.get("cpu_usage") or {}).get("total_usage", 0))
    system = cpu.get("system_cpu_usage", 0) - pre.get("system_cpu_usage", 0)
    online = cpu.get("online_cpus") or os.cpu_count() or 1
    if used <= 0 or system <= 0:
        return 0.0
    return float(used / system * online)


def measure(
    targets: list[tuple[tuple[str, str], int, CpuSeen]],
) -> dict[tuple[str, str], tuple[Usage, CpuSeen]]:
    """Sum CPU seconds, RSS and disk bytes over each component's process tree."""
    tree = _children_of if _PROC_CHILDREN else _children_map()
    measured: dict[tuple[str, str], tuple[Usage, CpuSeen]] = {}
    for key, root, seen in targets:
        usage = Usage()
        cpu_now: CpuSeen = {}
        stack = [root]
        while stack:
            pid = stack.pop()
            stack.extend(tree(pid))
            try:
                process = psutil.Process(pid)
                with process.oneshot():
                    times = process.cpu_times()
                    rss = process.memory_info().rss
                    ident = (pid, process.create_time())
            except psutil.Error:
                continue
            try:
                io = process.io_counters() if hasattr(process, "io_counters") else None
            except psutil.Error:  # e.g. a setuid child the agent may not inspect
                io = None
            cpu = times.user + times.system
            cpu_now[ident] = cpu
            usage.cpu += cpu - seen.get(ident, 0.0)
            usage.ram += rss
            if io is not None:
                usage.io_read += io.read_bytes
                usage.io_write += io.write_bytes
        usage.ram /= MIB
        measured[key] = (usage, cpu_now)
    return measured


# Linux lists each thread's children in /proc (CONFIG_PROC_CHILDREN): walking a component's tree from its
# root reads a few files, where listing every process of a robot (hundreds under ROS) costs a fifth of a
# core at four measurements a second.
_PROC_CHILDREN = os.path.exists(f"/proc/{os.getpid()}/task/{os.getpid()}/children")


def _children_of(pid: int) -> list[int]:
    """Return a process's children, read from its threads' /proc children lists."""
    found: list[int] = []
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return found  # gone
    for task in tasks:
        try:
            with open(f"/proc/{pid}/task/{task}/children", "rb") as listing:
                found.extend(int(child) for child in listing.read().split())
        except OSError:
            continue  # the thread ended meanwhile
    return found


def _children_map() -> Callable[[int], list[int]]:
    """Return every process's children from one pass over all processes (no /proc children lists here)."""
    children: dict[int, list[int]] = defaultdict(list)
    for process in psutil.process_iter(["ppid"]):
        children[process.info["ppid"]].append(process.pid)
    return lambda pid: children.get(pid, [])


def policy_from_label(text: str | None) -> RestartPolicy:
    """Read the restart policy a container was created with."""
    if not text:
        return RestartPolicy()
    try:
        return RestartPolicy(**json.loads(text))
    except (TypeError, ValueError):
        return RestartPolicy()


def sample_stats(api: Any, container_id: str) -> tuple[dict[str, Any], float]:
    """Take one stats sample of a container without Docker's one-second second sample."""
    raw = api.stats(container_id, stream=False, one_shot=True)
    return raw, time.time()
