"""Run each skill component as a local process group, restarted with backoff when it crashes.

Layout under ``data_dir``::

    work/<skill>/<component>/      the component's working directory
    logs/<skill>/<component>.log         its stdout (and .log.1, the rotated older part)
    logs/<skill>/<component>.stderr.log  its stderr (likewise)
    volumes/<skill>/<volume>/      the skill's volumes; BRIDGEOS_VOLUMES names volumes/<skill>

Each component is the leader of its own session, so stopping it signals its whole process
group, and it outlives an agent restart; the next agent re-adopts it with load_state. Its
output goes to files rather than to pipes the agent holds for the same reason: the agent's log
capture (``bridgeos_agent.logs``) follows them from where it stopped, and then keeps them small
itself (``log_sources``).

The agent watches exits through pidfds in its event loop (``runtime.groups``: one file
descriptor per component, no thread, no polling). asyncio's own subprocess support is not used
because Python 3.11 waits on every child with a thread of its own (ThreadedChildWatcher).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil
import pydantic

from bridgeos_agent.logs.capture import FileTail
from bridgeos_agent.runtime.base import (
    ACTIVE,
    VOLUMES_ENV,
    ComponentSpec,
    ComponentState,
    RestartBudget,
    RuntimeFailure,
    Status,
    StatusCallback,
    Usage,
    check_ids,
)
from bridgeos_agent.runtime.cgroups import Cgroups, ComponentGroup
from bridgeos_agent.runtime.groups import ExitWatcher, GroupLeader, adopt, group_alive, signal_group
from bridgeos_agent.runtime.lifecycle import Supervised, SupervisedRuntime
from bridgeos_agent.runtime.usage import MIB, CpuSeen, measure

__all__ = ["ProcessRuntime"]

logger = logging.getLogger(__name__)


# What a command needs from the agent's environment to be found and to run; everything
# else (tokens, the agent's own settings) stays out of components.
INHERITED_ENV = frozenset(
    {
        "PATH",
        "HOME",
        "LANG",
        "LANGUAGE",
        "TZ",
        "USER",
        "LOGNAME",
        "SHELL",
        "TMPDIR",
        "TERM",
        "LD_LIBRARY_PATH",
        "PYTHONPATH",
        "ROS_HOME",
        "ROS_LOG_DIR",
        "ROS_IP",
        "ROS_HOSTNAME",
        "ROS_PACKAGE_PATH",
        "ROS_DISTRO",
        "ROS_ROOT",
        "ROS_ETC_DIR",
        "ROS_PYTHON_VERSION",
        "ROS_VERSION",
    }
)


def _inherited_env() -> dict[str, str]:
    """Return the part of the agent's environment components inherit."""
    env = {k: v for k, v in os.environ.items() if k in INHERITED_ENV or k.startswith("LC_")}
    # The agent's own scripts (bridgeos-usecase) sit beside its interpreter: reachable even when
    # its venv is not activated, and last, so they never shadow what PATH already finds.
    scripts = os.path.dirname(sys.executable)
    path = env.get("PATH", os.defpath)
    if scripts and scripts not in path.split(os.pathsep):
        env["PATH"] = f"{path}{os.pathsep}{scripts}"
    return env


@dataclass(eq=False, slots=True, kw_only=True)
class _Component(Supervised):
    """Hold what the runtime knows and owns for one component."""

    spec: ComponentSpec
    proc: GroupLeader | None = None
    # CPU seconds seen per (pid, create_time) at the last stats() call, and its time.
    cpu_seen: CpuSeen = field(default_factory=dict)
    cpu_since: float | None = None
    # The control group holding it to its resources (None: limits not enforced, said in the log).
    group: ComponentGroup | None = None
    oom_kills_seen: int = 0


class ProcessRuntime(SupervisedRuntime[_Component]):
    """Launch components as local process groups (the embedded default runtime)."""

    name = "process"

    def __init__(
        self,
        robot: str,
        *,
        data_dir: Path,
        on_status: StatusCallback | None = None,
        log_max_bytes: int = 4 * MIB,
        log_check_interval: float = 30.0,
        use_pidfd: bool | None = None,
        poll_interval: float = 0.5,
        rng: random.Random | None = None,
        cgroups: Cgroups | None = None,
    ) -> None:
        super().__init__(robot, data_dir=data_dir, on_status=on_status, rng=rng or random.Random())
        self.cgroups = cgroups or Cgroups(robot)
        self.cgroups.sweep()  # empty groups of components killed while no agent watched
        logger.info("process runtime: component cpu/ram limits %s", self.cgroups.describe())
        self.log_max_bytes = log_max_bytes
        self.log_check_interval = log_check_interval
        self._watcher = ExitWatcher(
            use_pidfd=hasattr(os, "pidfd_open") if use_pidfd is None else use_pidfd,
            poll_interval=poll_interval,
        )
        self._base_env = _inherited_env()
        self._housekeeper: asyncio.Task[None] | None = None
        self._tails: dict[tuple[str, str], FileTail] = {}  # followed by the agent's log capture

    # --- paths ---------------------------------------------------------------------

    def work_dir(self, skill: str, component: str) -> Path:
        """Return a component's working directory."""
        return self.data_dir / "work" / skill / component

    def log_path(self, skill: str, component: str) -> Path:
        """Return the file a component's stdout goes to."""
        return self.data_dir / "logs" / skill / f"{component}.log"

    def stderr_path(self, skill: str, component: str) -> Path:
        """Return the file a component's stderr goes to."""
        return self.data_dir / "logs" / skill / f"{component}.stderr.log"

    def volumes_dir(self, skill: str) -> Path:
        """Return the directory holding a skill's volumes."""
        return self.data_dir / "volumes" / skill

    # --- the interface ---------------------------------------------------------------

    async def _read_logs(self, skill: str, component: str, tail: int) -> list[str]:
        """Return the last ``tail`` lines of a component's stdout, then stderr, even after it stopped.

        The files do not say how the two streams interleave; the agent's log rings do (``ring_lines``).
        """
        out, err = self.log_path(skill, component), self.stderr_path(skill, component)
        lines = await asyncio.to_thread(_tail, [out, _backup(out)], tail)
        lines += await asyncio.to_thread(_tail, [err, _backup(err)], tail)
        return lines[-tail:]

    def log_sources(self) -> dict[tuple[str, str], FileTail]:
        """Return the stdout and stderr files of every component, followed by the agent's log capture.

        From then on the capture empties a file it has read once it passes ``log_max_bytes``, in
        place of the housekeeper's copy and truncation, which would lose what it had not read yet.
        """
        for key in self._records:
            if key not in self._tails:
                files = {"stdout": self.log_path(*key), "stderr": self.stderr_path(*key)}
                self._tails[key] = FileTail(files, max_bytes=self.log_max_bytes)
        return {key: tail for key, tail in self._tails.items() if key in self._records}

    async def stats(self) -> dict[tuple[str, str], Usage]:
        """Measure every running component's process tree (see usage.measure)."""
        targets = [
            (key, comp.proc.pid, comp.cpu_seen)
            for key, comp in self._records.items()
            if comp.proc is not None and comp.state.status is Status.RUNNING
        ]
        if not targets:
            return {}
        measured = await asyncio.to_thread(measure, targets)
        now = time.time()
        result: dict[tuple[str, str], Usage] = {}
        for key, (usage, cpu_seen) in measured.items():
            comp = self._records.get(key)
            if comp is None:
                continue
            since = comp.cpu_since or comp.state.started_at or now
            usage.cpu /= max(now - since, 1e-3)
            comp.cpu_seen, comp.cpu_since = cpu_seen, now
            result[key] = usage
        return result

    def _saved(self, rec: _Component) -> dict[str, Any] | None:
        """Keep pid, start time and spec of a running component."""
        if rec.proc is None:
            return None
        return {"pid": rec.proc.pid, "create_time": rec.proc.create_time, "spec": rec.spec.to_dict()}

    async def load_state(self, state: Mapping[str, Any]) -> list[ComponentState]:
        """Re-adopt saved components whose process still runs (same pid and start time)."""
        if self._foreign(state):
            return []
        adopted: list[ComponentState] = []
        for entry in state.get("components", ()):
            try:
                spec = ComponentSpec.from_dict(entry["spec"])
                pid, create_time = int(entry["pid"]), float(entry["create_time"])
                check_ids(spec.skill, spec.component, spec.volumes)
            except (KeyError, TypeError, ValueError, pydantic.ValidationError) as exc:
                logger.warning("ignoring an unreadable saved component: %s", exc)
                continue
            current = self._records.get(spec.key)
            if current is not None and current.state.status in ACTIVE:
                continue
            proc = adopt(pid, create_time)
            if proc is None:
                continue
            comp = _Component(
                spec=spec,
                state=ComponentState(
                    skill=spec.skill,
                    component=spec.component,
                    status=Status.RUNNING,
                    pid_or_container_id=pid,
                    restarts=int(entry.get("restarts") or 0),
                    started_at=entry.get("started_at") or create_time,
                ),
                budget=RestartBudget(spec.restart),
                proc=proc,
                group=self.cgroups.group(spec),
            )
            if comp.group is not None:
                comp.oom_kills_seen = comp.group.oom_kills()
            self._records[spec.key] = comp
            self._ensure_housekeeper()
            self._watcher.watch(proc)
            self._watch(comp)
            adopted.append(dataclasses.replace(comp.state))
        return adopted

    def _background(self) -> list[asyncio.Task[None]]:
        """Return the log housekeeper, cancelled with the supervisors."""
        return [self._housekeeper] if self._housekeeper is not None else []

    async def _release(self) -> None:
        """Stop watching exits: the components keep running."""
        await self._watcher.close()

    # --- launching and supervising ---------------------------------------------------

    def _ensure_housekeeper(self) -> None:
        """Start the one task that rotates every component's log."""
        if self._housekeeper is None:
            self._housekeeper = asyncio.create_task(self._rotate_logs_forever(), name="bridgeos-process-logs")

    def _env(self, spec: ComponentSpec) -> dict[str, str]:
        """Build a component's environment: inherited basics, launch env, contract env."""
        return {
            **self._base_env,
            # Python components' prints should reach the log as they happen, not at exit.
            "PYTHONUNBUFFERED": "1",
            **spec.launch_env(),
            VOLUMES_ENV: str(self.volumes_dir(spec.skill)),
        }

    def _new_record(self, spec: ComponentSpec) -> _Component:
        """Return the record of a component about to be launched."""
        self._ensure_housekeeper()
        return _Component(
            spec=spec,
            state=ComponentState(skill=spec.skill, component=spec.component, status=Status.STARTING),
            budget=RestartBudget(spec.restart),
        )

    async def _launch_first(self, rec: _Component, spec: ComponentSpec) -> None:
        """Spawn the component: at once, with no wait between its record and its process."""
        self._launch(rec)

    async def _relaunch(self, rec: _Component) -> None:
        """Spawn the crashed component again."""
        self._launch(rec)

    def _exited(self, rec: _Component) -> asyncio.Future[int | None] | None:
        """Return the future of the component's process exit."""
        return rec.proc.exited if rec.proc is not None else None

    def _reap(self, rec: _Component) -> None:
        """Kill what the exited leader left behind."""
        if rec.proc is not None:
            # What the leader leaves behind dies with it, as in a container; a relaunch
            # must not run next to the last launch's orphans.
            signal_group(rec.proc.pid, signal.SIGKILL)
            rec.proc = None

    def _command(self, rec: _Component) -> list[str] | None:
        """Return the component's command."""
        return rec.spec.launch.command

    async def _end(self, rec: _Component, timeout: float) -> None:
        """Stop the component's whole process group, then delete its control group."""
        if rec.proc is not None:
            rec.state.exit_code = await self._terminate(rec.proc, timeout)
            rec.proc = None
        if rec.group is not None:
            await rec.group.remove()

    async def _aside(self, rec: _Component, aside: bool) -> None:
        """Move the component's control group out of the way of a new version's (or back)."""
        if rec.group is None:
            return
        try:
            rec.group.rename(".aside", back=not aside)
        except OSError as exc:
            # Shared with the new version's then: its limits hold both, and it is left in place at the stop.
            logger.warning("control group of %s/%s not set aside: %s", rec.spec.skill, rec.spec.component, exc)
            rec.group = None

    async def _finished(self, rec: _Component) -> None:
        """Delete the control group of a component that will not be relaunched."""
        if rec.group is not None:
            await rec.group.remove()

    def _exit_reason(self, rec: _Component, code: int | None) -> str | None:
        """Say when the kernel killed the component for going over its memory limit."""
        if rec.group is None:
            return None
        kills = rec.group.oom_kills()
        if kills <= rec.oom_kills_seen:
            return None
        rec.oom_kills_seen = kills
        return (
            f"killed by the kernel (exit {code}): it went over its memory limit of "
            f"{rec.spec.resources.ram:g} MiB (out of memory)"
        )

    def _launch(self, comp: _Component) -> GroupLeader:
        """Spawn the component's command in a new session, logging to its file."""
        spec = comp.spec
        who = f"component {spec.skill}/{spec.component}"
        command = spec.launch.command
        if not command:
            raise RuntimeFailure(
                f"{who} has no command for the process runtime (its launch spec only names image "
                f"{spec.launch.image!r}): add a 'command' to its robot launch spec, or run the agent "
                "with --runtime docker"
            )
        cwd = self.work_dir(spec.skill, spec.component)
        log = self.log_path(spec.skill, spec.component)
        errors = self.stderr_path(spec.skill, spec.component)
        cwd.mkdir(parents=True, exist_ok=True)
        log.parent.mkdir(parents=True, exist_ok=True)
        for volume in spec.volumes:
            (self.volumes_dir(spec.skill) / volume).mkdir(parents=True, exist_ok=True)
        _rotate(log, self.log_max_bytes, copy=False)
        _rotate(errors, self.log_max_bytes, copy=False)
        comp.group = self.cgroups.prepare(spec)
        out = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC, 0o644)
        fd = os.open(errors, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC, 0o644)
        try:
            popen = self._spawn(comp, command, out, fd, cwd)
        except FileNotFoundError:
            message = (
                f"{who}: command {command[0]!r} not found (looked in PATH={self._base_env.get('PATH', '')!r}): "
                "install it or fix the command in the skill's robot launch spec"
            )
            _log_failure(fd, message)
            raise RuntimeFailure(message) from None
        except PermissionError:
            message = f"{who}: command {command[0]!r} is not executable: chmod +x it or fix the launch spec"
            _log_failure(fd, message)
            raise RuntimeFailure(message) from None
        except OSError as exc:
            message = f"{who}: cannot run {command[0]!r}: {exc}"
            _log_failure(fd, message)
            raise RuntimeFailure(message) from None
        except subprocess.SubprocessError as exc:
            message = f"{who}: cannot join its control group {comp.group and comp.group.directories}: {exc}"
            _log_failure(fd, message)
            raise RuntimeFailure(message) from None
        finally:
            os.close(out)
            os.close(fd)
        try:
            create_time = psutil.Process(popen.pid).create_time()
        except psutil.Error:
            create_time = time.time()
        proc = GroupLeader(
            pid=popen.pid,
            create_time=create_time,
            exited=asyncio.get_running_loop().create_future(),
            popen=popen,
        )
        comp.proc = proc
        self._watcher.watch(proc)
        state = comp.state
        state.status = Status.RUNNING
        state.pid_or_container_id = popen.pid
        state.exit_code = None
        state.message = None
        state.started_at = time.time()
        return proc

    def _spawn(self, comp: _Component, command: list[str], out: int, err: int, cwd: Path) -> subprocess.Popen[bytes]:
        """Start the command in a session of its own, inside the component's group when it has one."""
        for attempt in (1, 2):
            try:
                return subprocess.Popen(
                    command,
                    stdin=subprocess.DEVNULL,
                    stdout=out,
                    stderr=err,
                    cwd=cwd,
                    env=self._env(comp.spec),
                    start_new_session=True,
                    # Joined before exec, so nothing the command forks starts outside its limits.
                    preexec_fn=comp.group.joiner() if comp.group is not None else None,
                )
            except subprocess.SubprocessError:
                # The group went between its making and the join (another process of this robot
                # deleted it as it stopped its last component): made again, joined once more.
                if attempt == 2 or comp.group is None:
                    raise
                comp.group = self.cgroups.prepare(comp.spec)
        raise AssertionError("unreachable")

    async def _terminate(self, proc: GroupLeader, timeout: float) -> int | None:
        """Signal a process group to stop, then kill whatever is left after ``timeout``."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        signal_group(proc.pid, signal.SIGTERM)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(asyncio.shield(proc.exited), timeout)
        # Members that outlive the leader get what is left of the timeout, then SIGKILL.
        # Nothing signals a group's end (they are not our children), so look every 50 ms.
        while loop.time() < deadline and group_alive(proc.pid):  # noqa: ASYNC110
            await asyncio.sleep(0.05)
        signal_group(proc.pid, signal.SIGKILL)
        return await asyncio.shield(proc.exited)

    async def _rotate_logs_forever(self) -> None:
        """Keep every running component's log under the size limit."""
        while True:
            await asyncio.sleep(self.log_check_interval)
            paths = [
                path
                for key, comp in self._records.items()
                if comp.state.status in ACTIVE and key not in self._tails  # the capture keeps those small
                for path in (self.log_path(*key), self.stderr_path(*key))
            ]
            await asyncio.to_thread(_rotate_all, paths, self.log_max_bytes)


def _log_failure(fd: int, message: str) -> None:
    """Write why a launch failed into the component's stderr log, where operators look."""
    with contextlib.suppress(OSError):
        os.write(fd, f"[bridgeos] {message}\n".encode())


def _backup(path: Path) -> Path:
    """Return the rotated older part of a log."""
    return path.with_name(path.name + ".1")


def _rotate(path: Path, max_bytes: int, *, copy: bool) -> None:
    """Move a log's content to its backup once it grows past ``max_bytes``.

    A running component keeps its file open, so its log is copied and truncated in place
    (its appends continue at the new end); before a launch the file is simply renamed.
    """
    try:
        if path.stat().st_size <= max_bytes:
            return
        if copy:
            shutil.copyfile(path, _backup(path))
            os.truncate(path, 0)
        else:
            os.replace(path, _backup(path))
    except FileNotFoundError:
        pass


def _rotate_all(paths: list[Path], max_bytes: int) -> None:
    """Rotate every oversized log of the running components."""
    for path in paths:
        try:
            _rotate(path, max_bytes, copy=True)
        except OSError as exc:
            logger.warning("cannot rotate %s: %s", path, exc)


def _tail(paths: list[Path], count: int) -> list[str]:
    """Return the last ``count`` lines of the newest file, then of older ones if needed."""
    lines: list[str] = []
    for path in paths:
        try:
            with path.open("rb") as file:
                chunk = _read_tail(file, count - len(lines))
        except FileNotFoundError:
            continue
        # A file the log capture punched holes in reads as NUL bytes there.
        lines = chunk.lstrip(b"\0").decode("utf-8", errors="replace").splitlines()[-(count - len(lines)) :] + lines
        if len(lines) >= count:
            break
    return lines[-count:]


def _read_tail(file: Any, count: int, block: int = 8192) -> bytes:
    """Read backwards from the end of a file until it holds ``count`` full lines."""
    end = file.seek(0, os.SEEK_END)
    data = b""
    position = end
    while position > 0 and data.count(b"\n") <= count:
        step = min(block, position)
        position -= step
        file.seek(position)
        data = file.read(step) + data
    return data
