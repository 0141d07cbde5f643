"""Hold a process component to its declared ``resources`` with Linux control groups.

The Docker runtime gets CPU and memory limits from Docker; the process runtime gets them here:
one group per component, ``bridgeos/<robot>/<skill>.<component>`` under the agent's own
group, with cgroup v2 (``cpu.max``, ``memory.max``) when its cpu and memory controllers are
available, else cgroup v1 (``cpu.cfs_quota_us``, ``memory.limit_in_bytes``). The launched
process joins its group before it runs the component's command, so nothing it forks escapes.
Where neither can be used the agent says once that limits are not enforced, and runs anyway.

The arithmetic (quota from cores, bytes from MiB, where the hierarchies are) is pure
functions over text; ``Cgroups`` and ``ComponentGroup`` do the file-system side.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import os
import re
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from bridgeos_agent.runtime.base import ComponentSpec
from bridgeos_agent.skillconfig import ComponentResources

__all__ = [
    "CPU_PERIOD_US",
    "Cgroups",
    "ComponentGroup",
    "Hierarchy",
    "Limits",
    "cpu_quota_us",
    "find_hierarchy",
    "limits_for",
    "memory_limit_bytes",
]

logger = logging.getLogger(__name__)

MIB = 1024 * 1024
CPU_PERIOD_US = 100_000
MIN_QUOTA_US = 1_000  # the kernel refuses quotas under 1 ms
MIN_MEMORY = 6 * MIB  # as the Docker runtime: smaller limits kill a process before it starts
SWEEP_MIN_AGE_S = 60.0
CONTROLLERS = ("cpu", "memory")

Version = Literal["v1", "v2"]


@dataclass(frozen=True, slots=True)
class Limits:
    """Say what a component's group enforces: a CPU quota per period and a memory ceiling."""

    cpu_quota_us: int | None
    cpu_period_us: int
    memory_bytes: int | None

    @property
    def any(self) -> bool:
        return self.cpu_quota_us is not None or self.memory_bytes is not None


def cpu_quota_us(cpu: float, *, cpus: int | None = None, period_us: int = CPU_PERIOD_US) -> int | None:
    """Turn cores into the CFS quota per period (None: no CPU limit)."""
    if cpu <= 0:
        return None
    # More cores than the machine has is no limit at all: cap it, as Docker does.
    cores = min(cpu, float(cpus or os.cpu_count() or 1))
    return max(MIN_QUOTA_US, round(cores * period_us))


def memory_limit_bytes(ram_mib: float) -> int | None:
    """Turn MiB into the memory ceiling in bytes (None: no memory limit)."""
    if ram_mib <= 0:
        return None
    return max(int(ram_mib * MIB), MIN_MEMORY)


def limits_for(resources: ComponentResources, *, cpus: int | None = None) -> Limits:
    """Return the limits a component's declared resources ask for."""
    return Limits(cpu_quota_us(resources.cpu, cpus=cpus), CPU_PERIOD_US, memory_limit_bytes(resources.ram))


@dataclass(frozen=True, slots=True)
class Hierarchy:
    """Where the agent's component groups go: one base directory per controller (one for v2)."""

    version: Version
    bases: Mapping[str, Path]  # controller -> the agent's own group directory


def find_hierarchy(mounts: str, own: str, *, v2_controllers: Callable[[Path], str]) -> Hierarchy | None:
    """Find the cgroup hierarchy with cpu and memory, from /proc/self/mounts and /proc/self/cgroup text."""
    own_paths: dict[str, str] = {}
    for line in own.splitlines():
        parts = line.split(":", 2)
        if len(parts) == 3:
            for controller in parts[1].split(",") if parts[1] else [""]:
                own_paths[controller] = parts[2]
    v1: dict[str, Path] = {}
    v2_mount: Path | None = None
    for line in mounts.splitlines():
        fields = line.split()
        if len(fields) < 4:
            continue
        mount_point, kind, options = _unescape(fields[1]), fields[2], fields[3].split(",")
        if kind == "cgroup2":
            v2_mount = Path(mount_point)
        elif kind == "cgroup":
            for controller in CONTROLLERS:
                if controller in options and controller in own_paths:
                    v1[controller] = Path(mount_point) / own_paths[controller].lstrip("/")
    if v2_mount is not None and set(CONTROLLERS) <= set(v2_controllers(v2_mount).split()):
        # The root group is the only one free of v2's "no processes in inner groups" rule, so
        # the agent's groups hang from it rather than from the agent's own (populated) group.
        return Hierarchy("v2", {"": v2_mount})
    if v1:
        return Hierarchy("v1", v1)
    return None


def _unescape(path: str) -> str:
    """Undo /proc/mounts' octal escapes (a space is \\040)."""
    return re.sub(r"\\([0-7]{3})", lambda m: chr(int(m.group(1), 8)), path)


def _read_controllers(mount: Path) -> str:
    try:
        return (mount / "cgroup.controllers").read_text()
    except OSError:
        return ""


def _write(path: Path, value: str) -> None:
    path.write_text(value)


class ComponentGroup:
    """One component's control group: created with its limits, joined at launch, removed at stop."""

    def __init__(self, version: Version, directories: Mapping[str, Path], limits: Limits) -> None:
        self.version = version
        self.directories = dict(directories)  # controller -> directory ("" for v2)
        self.limits = limits

    def rename(self, suffix: str, *, back: bool = False) -> None:
        """Move the group, its processes with it, to its name plus ``suffix`` (or back from there)."""
        moved = {}
        for key, directory in self.directories.items():
            target = directory.with_name(directory.name.removesuffix(suffix) if back else directory.name + suffix)
            with contextlib.suppress(FileNotFoundError):
                target.rmdir()  # an empty group left there (a launch that failed, an agent killed): never a live one
            moved[key] = directory.rename(target)
        self.directories = moved

    def create(self) -> None:
        """Make the group (idempotent) and write its limits."""
        for directory in self.directories.values():
            directory.mkdir(parents=True, exist_ok=True)
        limits = self.limits
        if self.version == "v2":
            (directory,) = self.directories.values()
            quota = "max" if limits.cpu_quota_us is None else str(limits.cpu_quota_us)
            _write(directory / "cpu.max", f"{quota} {limits.cpu_period_us}")
            _write(directory / "memory.max", "max" if limits.memory_bytes is None else str(limits.memory_bytes))
            # No swap: a component over its memory must be stopped, not slowed down to a crawl.
            with contextlib.suppress(FileNotFoundError):
                _write(directory / "memory.swap.max", "0" if limits.memory_bytes is not None else "max")
            return
        cpu = self.directories.get("cpu")
        if cpu is not None:
            _write(cpu / "cpu.cfs_period_us", str(limits.cpu_period_us))
            _write(cpu / "cpu.cfs_quota_us", "-1" if limits.cpu_quota_us is None else str(limits.cpu_quota_us))
        memory = self.directories.get("memory")
        if memory is not None:
            value = "-1" if limits.memory_bytes is None else str(limits.memory_bytes)
            swap = memory / "memory.memsw.limit_in_bytes"
            if swap.exists():
                # memsw must stay >= the plain limit: lower it after, raise it before.
                order = [memory / "memory.limit_in_bytes", swap]
                if limits.memory_bytes is None:
                    order.reverse()
                for path in order:
                    _write(path, value)
            else:
                _write(memory / "memory.limit_in_bytes", value)

    def procs_files(self) -> list[bytes]:
        """Return the cgroup.procs files a launched process writes itself into."""
        return [os.fsencode(directory / "cgroup.procs") for directory in self.directories.values()]

    def joiner(self) -> Callable[[], None]:
        """Return what the forked child runs before exec to join the group (os calls only: it runs after fork)."""
        files = self.procs_files()

        def join() -> None:
            for name in files:
                fd = os.open(name, os.O_WRONLY)
                try:
                    os.write(fd, b"0")  # 0: the writing process itself
                finally:
                    os.close(fd)

        return join

    def members(self) -> set[int]:
        """Return the pids in the group."""
        pids: set[int] = set()
        for directory in self.directories.values():
            with contextlib.suppress(OSError):
                pids |= {int(p) for p in (directory / "cgroup.procs").read_text().split()}
        return pids

    def oom_kills(self) -> int:
        """Count the processes the kernel killed in this group for exceeding its memory limit."""
        directory = self.directories.get("" if self.version == "v2" else "memory")
        if directory is None:
            return 0
        name = "memory.events" if self.version == "v2" else "memory.oom_control"
        try:
            text = (directory / name).read_text()
        except OSError:
            return 0
        match = re.search(r"^oom_kill (\d+)$", text, re.M)
        return int(match.group(1)) if match else 0

    async def remove(self, timeout: float = 2.0) -> bool:
        """Delete the group once its processes are gone; return whether it is gone."""
        deadline = asyncio.get_running_loop().time() + timeout
        left = dict(self.directories)
        while left:
            for key, directory in list(left.items()):
                try:
                    directory.rmdir()
                except FileNotFoundError:
                    pass
                except OSError as exc:
                    # EBUSY while the killed members are still being torn down by the kernel.
                    if exc.errno != errno.EBUSY:
                        logger.warning("cannot remove control group %s: %s", directory, exc)
                        return False
                    continue
                del left[key]
            if not left:
                for directory in self.directories.values():
                    # The robot's and the agent's directories go with their last component.
                    for parent in (directory.parent, directory.parent.parent):
                        try:
                            parent.rmdir()
                        except OSError:
                            break
                return True
            if asyncio.get_running_loop().time() > deadline:
                logger.warning(
                    "control group %s still has processes; left in place", ", ".join(map(str, left.values()))
                )
                return False
            await asyncio.sleep(0.05)
        return True


class Cgroups:
    """Make the component groups of one robot's agent, or say once why limits are not enforced."""

    def __init__(
        self,
        robot: str,
        *,
        hierarchy: Hierarchy | Literal["detect"] | None = "detect",
        cpus: int | None = None,
    ) -> None:
        self.robot = robot
        self.cpus = cpus
        self.hierarchy = _detect() if hierarchy == "detect" else hierarchy
        self._unenforced_said = False
        self._failures_said: set[str] = set()
        if self.hierarchy is not None and self.hierarchy.version == "v1":
            for missing in (c for c in CONTROLLERS if c not in self.hierarchy.bases):
                logger.warning("component %s limits are NOT enforced: no cgroup v1 %s hierarchy", missing, missing)

    @property
    def version(self) -> Version | None:
        return self.hierarchy.version if self.hierarchy is not None else None

    def describe(self) -> str:
        """Say how component limits are enforced, in one line for the agent's log."""
        if self.hierarchy is None:
            return "not enforced (no writable cgroup v2 or v1 cpu/memory controllers)"
        bases = ", ".join(str(p) for p in self.hierarchy.bases.values())
        return f"cgroup {self.hierarchy.version} under {bases}"

    def group(self, spec: ComponentSpec) -> ComponentGroup | None:
        """Return the (not yet created) group of a component, or None when nothing can be enforced."""
        limits = limits_for(spec.resources, cpus=self.cpus)
        if self.hierarchy is None:
            if limits.any:
                self._say_unenforced()
            return None
        # The location keeps a robot's copy and the cloud's copy apart when both run on one host.
        leaf = f"{spec.skill}.{spec.component}.{spec.location}"
        directories = {c: base / "bridgeos" / self.robot / leaf for c, base in self.hierarchy.bases.items()}
        return ComponentGroup(self.hierarchy.version, directories, limits)

    def prepare(self, spec: ComponentSpec) -> ComponentGroup | None:
        """Create a component's group with its limits; None (said once) when that cannot be done."""
        group = self.group(spec)
        if group is None:
            return None
        try:
            for attempt in (1, 2):
                try:
                    if self.hierarchy is not None and self.hierarchy.version == "v2":
                        self._enable_v2(next(iter(group.directories.values())).parent)
                    group.create()
                    break
                except FileNotFoundError:
                    # A parent went meanwhile (another process of this robot stopped its last component).
                    if attempt == 2:
                        raise
        except OSError as exc:
            reason = f"{type(exc).__name__}: {exc}"
            if reason not in self._failures_said:
                self._failures_said.add(reason)
                logger.warning(
                    "component resource limits are NOT enforced for %s/%s: cannot set up its control group (%s)",
                    spec.skill,
                    spec.component,
                    reason,
                )
            return None
        return group

    def sweep(self, min_age_s: float = SWEEP_MIN_AGE_S) -> int:
        """Delete this robot's empty, older component groups (a populated one cannot be); return how many."""
        if self.hierarchy is None:
            return 0
        removed = 0
        for base in self.hierarchy.bases.values():
            robot_dir = base / "bridgeos" / self.robot
            try:
                leaves = [p for p in robot_dir.iterdir() if p.is_dir()]
            except OSError:
                continue
            for leaf in leaves:
                try:
                    # A group made in the last minute may belong to a launch in progress in another
                    # process of this robot (the cloud's worker pool): left for a later sweep.
                    if time.time() - leaf.stat().st_mtime < min_age_s:
                        continue
                    leaf.rmdir()
                except OSError:
                    continue  # still running: an adopted component's group
                removed += 1
            with contextlib.suppress(OSError):
                robot_dir.rmdir()
        return removed

    def _enable_v2(self, robot_dir: Path) -> None:
        """Hand the cpu and memory controllers down from the root to the robot's group."""
        assert self.hierarchy is not None
        root = self.hierarchy.bases[""]
        path = root
        for part in robot_dir.relative_to(root).parts:
            _write(path / "cgroup.subtree_control", " ".join(f"+{c}" for c in CONTROLLERS))
            path = path / part
            path.mkdir(exist_ok=True)
        _write(path / "cgroup.subtree_control", " ".join(f"+{c}" for c in CONTROLLERS))

    def _say_unenforced(self) -> None:
        if not self._unenforced_said:
            self._unenforced_said = True
            logger.warning(
                "component resource limits (cpu, ram) are NOT enforced by the process runtime: no writable "
                "cgroup v2 with cpu and memory controllers and no cgroup v1 cpu/memory hierarchy here; "
                "run the agent as root on a machine with cgroups, or use --runtime docker"
            )


def _detect() -> Hierarchy | None:
    """Find a usable hierarchy for this process, checking that it can be written."""
    try:
        mounts = Path("/proc/self/mounts").read_text()
        own = Path("/proc/self/cgroup").read_text()
    except OSError:
        return None
    hierarchy = find_hierarchy(mounts, own, v2_controllers=_read_controllers)
    if hierarchy is None or not all(_writable(p) for p in hierarchy.bases.values()):
        return None
    return hierarchy


def _writable(path: Path) -> bool:
    return os.access(path, os.W_OK | os.X_OK)
