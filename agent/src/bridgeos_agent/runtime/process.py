"""Run each skill component as a local process group, restarted with backoff when it crashes.

Layout under ``data_dir``::

    work/<skill>/<component>/      the component's working directory
    logs/<skill>/<component>.log   its stdout and stderr (and .log.1, the rotated older part)
    volumes/<skill>/<volume>/      the skill's volumes; BRIDGEOS_VOLUMES names volumes/<skill>

Each component is the leader of its own session, so stopping it signals its whole process
group, and it outlives an agent restart; the next agent re-adopts it with load_state.

The agent watches exits through pidfds in its event loop (one file descriptor per component,
no thread, no polling). asyncio's own subprocess support is not used because Python 3.11
waits on every child with a thread of its own (ThreadedChildWatcher).
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import errno
import logging
import math
import os
import random
import shutil
import signal
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import psutil
import pydantic

from bridgeos_agent.runtime.base import (
    ACTIVE,
    VOLUMES_ENV,
    ComponentSpec,
    ComponentState,
    RestartBudget,
    Runtime,
    RuntimeFailure,
    Status,
    StatusCallback,
    Usage,
    absent,
    check_ids,
    exit_code,
    give_up_message,
    unrunnable,
)

__all__ = ["ProcessRuntime"]

logger = logging.getLogger(__name__)

MIB = 1024 * 1024

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


@dataclass(eq=False, slots=True)
class _Proc:
    """Track one launched (or adopted) process-group leader until it exits."""

    pid: int
    create_time: float
    exited: asyncio.Future[int | None]
    popen: subprocess.Popen[bytes] | None = None  # None when adopted from an earlier agent
    handle: psutil.Process | None = None  # kept to check an adopted process by polling
    pidfd: int | None = None

    def running(self) -> bool:
        """Say whether the process still runs (polling fallback only)."""
        if self.popen is not None:
            return self.popen.poll() is None
        if self.handle is None:
            self.handle = psutil.Process(self.pid)
        try:
            return self.handle.is_running() and self.handle.status() != psutil.STATUS_ZOMBIE
        except psutil.Error:
            return False

    def exit_status(self) -> int | None:
        """Reap the exited process and return its exit code, or None if it is not our child."""
        if self.popen is not None:
            returncode = self.popen.poll()
            return None if returncode is None else exit_code(returncode)
        # An adopted process is normally init's child now; in the agent that launched it
        # (tests, an in-process restart) it is still ours and must be reaped here.
        with contextlib.suppress(ChildProcessError):
            pid, status = os.waitpid(self.pid, os.WNOHANG)
            if pid:
                return exit_code(os.waitstatus_to_exitcode(status))
        return None

    def finish(self) -> None:
        """Resolve the exit future with the exit code, if known."""
        code = self.exit_status()
        if not self.exited.done():
            self.exited.set_result(code)


class _ExitWatcher:
    """Resolve each watched process's exit future: pidfd readiness, or one shared poll."""

    def __init__(self, *, use_pidfd: bool, poll_interval: float) -> None:
        self._use_pidfd = use_pidfd
        self._poll_interval = poll_interval
        self._pidfds: dict[int, _Proc] = {}
        self._polled: set[_Proc] = set()
        self._poller: asyncio.Task[None] | None = None

    def watch(self, proc: _Proc) -> None:
        """Start watching a process for its exit."""
        loop = asyncio.get_running_loop()
        if self._use_pidfd:
            try:
                pidfd = os.pidfd_open(proc.pid)
            except OSError as exc:
                if exc.errno == errno.ESRCH:  # gone (and reaped) already
                    proc.finish()
                    return
                logger.warning("pidfd_open failed (%s); watching processes by polling", exc)
                self._use_pidfd = False
            else:
                proc.pidfd = pidfd
                self._pidfds[pidfd] = proc
                loop.add_reader(pidfd, self._on_exit, proc)
                return
        self._polled.add(proc)
        if self._poller is None or self._poller.done():
            self._poller = asyncio.create_task(self._poll(), name="bridgeos-process-poller")

    def _forget(self, proc: _Proc) -> None:
        """Stop watching a process and release its pidfd."""
        self._polled.discard(proc)
        if proc.pidfd is not None:
            asyncio.get_running_loop().remove_reader(proc.pidfd)
            os.close(proc.pidfd)
            del self._pidfds[proc.pidfd]
            proc.pidfd = None

    def _on_exit(self, proc: _Proc) -> None:
        """Handle a pidfd turning readable: its process has exited."""
        self._forget(proc)
        proc.finish()

    async def _poll(self) -> None:
        """Check every polled process at a fixed interval."""
        while self._polled:
            await asyncio.sleep(self._poll_interval)
            for proc in [p for p in self._polled if not p.running()]:
                self._forget(proc)
                proc.finish()

    async def close(self) -> None:
        """Stop watching everything; the processes keep running."""
        for proc in [*self._pidfds.values(), *self._polled]:
            self._forget(proc)
        if self._poller is not None:
            self._poller.cancel()
            await asyncio.wait([self._poller])


@dataclass(eq=False, slots=True)
class _Component:
    """Hold what the runtime knows and owns for one component."""

    spec: ComponentSpec
    state: ComponentState
    budget: RestartBudget
    proc: _Proc | None = None
    supervisor: asyncio.Task[None] | None = None
    stop_done: asyncio.Future[None] | None = None
    # CPU seconds seen per (pid, create_time) at the last stats() call, and its time.
    cpu_seen: dict[tuple[int, float], float] = field(default_factory=dict)
    cpu_since: float | None = None


class ProcessRuntime(Runtime):
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
    ) -> None:
        super().__init__(robot, data_dir=data_dir, on_status=on_status)
        self.log_max_bytes = log_max_bytes
        self.log_check_interval = log_check_interval
        self._components: dict[tuple[str, str], _Component] = {}
        self._watcher = _ExitWatcher(
            use_pidfd=hasattr(os, "pidfd_open") if use_pidfd is None else use_pidfd,
            poll_interval=poll_interval,
        )
        self._rng = rng or random.Random()
        self._base_env = _inherited_env()
        self._housekeeper: asyncio.Task[None] | None = None

    # --- paths ---------------------------------------------------------------------

    def work_dir(self, skill: str, component: str) -> Path:
        """Return a component's working directory."""
        return self.data_dir / "work" / skill / component

    def log_path(self, skill: str, component: str) -> Path:
        """Return the file a component's stdout and stderr go to."""
        return self.data_dir / "logs" / skill / f"{component}.log"

    def volumes_dir(self, skill: str) -> Path:
        """Return the directory holding a skill's volumes."""
        return self.data_dir / "volumes" / skill

    # --- the interface ---------------------------------------------------------------

    async def start(self, spec: ComponentSpec) -> ComponentState:
        """Launch a component, or return its state if it is already running."""
        check_ids(spec.skill, spec.component, spec.volumes)
        key = spec.key
        current = self._components.get(key)
        while current is not None and current.stop_done is not None and not current.stop_done.done():
            await asyncio.shield(current.stop_done)
            current = self._components.get(key)
        if current is not None and current.state.status in ACTIVE:
            return dataclasses.replace(current.state)
        self._ensure_housekeeper()
        comp = _Component(
            spec=spec,
            state=ComponentState(skill=spec.skill, component=spec.component, status=Status.STARTING),
            budget=RestartBudget(spec.restart),
        )
        self._components[key] = comp
        self._notify(comp.state)
        try:
            self._launch(comp)
        except RuntimeFailure as exc:
            comp.state.status = Status.FAILED
            comp.state.message = str(exc)
            self._notify(comp.state)
            raise
        self._notify(comp.state)
        comp.supervisor = asyncio.create_task(
            self._supervise(comp), name=f"bridgeos-process-{spec.skill}/{spec.component}"
        )
        return dataclasses.replace(comp.state)

    async def stop(self, skill: str, component: str, timeout: float = 10.0) -> ComponentState:
        """Stop a component's whole process group: SIGTERM, then SIGKILL after ``timeout``."""
        check_ids(skill, component)
        comp = self._components.get((skill, component))
        if comp is None:
            return absent(skill, component)
        if comp.stop_done is not None:
            await asyncio.shield(comp.stop_done)
            return dataclasses.replace(comp.state)
        comp.stop_done = asyncio.get_running_loop().create_future()
        try:
            if comp.supervisor is not None:
                # Cancelled first, so the exit our signal causes is never taken for a crash.
                comp.supervisor.cancel()
                await asyncio.wait([comp.supervisor])
            if comp.proc is not None:
                comp.state.exit_code = await self._terminate(comp.proc, timeout)
                comp.proc = None
            comp.state.status = Status.STOPPED
            self._notify(comp.state)
        finally:
            comp.stop_done.set_result(None)
        return dataclasses.replace(comp.state)

    async def status(self, skill: str, component: str) -> ComponentState:
        """Return a component's current state (status 'absent' if unknown)."""
        comp = self._components.get((skill, component))
        return absent(skill, component) if comp is None else dataclasses.replace(comp.state)

    async def logs(self, skill: str, component: str, tail: int = 100) -> list[str]:
        """Return the last ``tail`` lines of a component's log, even after it stopped."""
        check_ids(skill, component)
        if tail <= 0:
            return []
        path = self.log_path(skill, component)
        return await asyncio.to_thread(_tail, [path, _backup(path)], tail)

    async def stats(self) -> dict[tuple[str, str], Usage]:
        """Measure every running component's process tree in one pass over the process table."""
        targets = [
            (key, comp.proc.pid, comp.cpu_seen)
            for key, comp in self._components.items()
            if comp.proc is not None and comp.state.status is Status.RUNNING
        ]
        if not targets:
            return {}
        measured = await asyncio.to_thread(_measure, targets)
        now = time.time()
        result: dict[tuple[str, str], Usage] = {}
        for key, (usage, cpu_seen) in measured.items():
            comp = self._components.get(key)
            if comp is None:
                continue
            since = comp.cpu_since or comp.state.started_at or now
            usage.cpu /= max(now - since, 1e-3)
            comp.cpu_seen, comp.cpu_since = cpu_seen, now
            result[key] = usage
        return result

    def get_state(self) -> dict[str, Any]:
        """Return pid, start time and spec of every running component."""
        return {
            "runtime": self.name,
            "robot": self.robot,
            "components": [
                {
                    "skill": comp.spec.skill,
                    "component": comp.spec.component,
                    "pid": comp.proc.pid,
                    "create_time": comp.proc.create_time,
                    "restarts": comp.state.restarts,
                    "started_at": comp.state.started_at,
                    "spec": comp.spec.to_dict(),
                }
                for comp in self._components.values()
                if comp.proc is not None and comp.state.status is Status.RUNNING
            ],
        }

    async def load_state(self, state: Mapping[str, Any]) -> list[ComponentState]:
        """Re-adopt saved components whose process still runs (same pid and start time)."""
        if state.get("runtime", self.name) != self.name:
            logger.warning("ignoring saved state of the %r runtime", state.get("runtime"))
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
            current = self._components.get(spec.key)
            if current is not None and current.state.status in ACTIVE:
                continue
            proc = _adopt(pid, create_time)
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
            )
            self._components[spec.key] = comp
            self._ensure_housekeeper()
            self._watcher.watch(proc)
            comp.supervisor = asyncio.create_task(
                self._supervise(comp), name=f"bridgeos-process-{spec.skill}/{spec.component}"
            )
            adopted.append(dataclasses.replace(comp.state))
        return adopted

    async def close(self, stop_components: bool = False) -> None:
        """Stop supervising; stop the components too if asked, else leave them running."""
        if stop_components:
            await asyncio.gather(
                *(self.stop(*key) for key, comp in self._components.items() if comp.state.status in ACTIVE)
            )
        tasks = [comp.supervisor for comp in self._components.values() if comp.supervisor is not None]
        if self._housekeeper is not None:
            tasks.append(self._housekeeper)
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.wait(tasks)
        await self._watcher.close()
        self._components.clear()

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

    def _launch(self, comp: _Component) -> _Proc:
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
        cwd.mkdir(parents=True, exist_ok=True)
        log.parent.mkdir(parents=True, exist_ok=True)
        for volume in spec.volumes:
            (self.volumes_dir(spec.skill) / volume).mkdir(parents=True, exist_ok=True)
        _rotate(log, self.log_max_bytes, copy=False)
        fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND | os.O_CLOEXEC, 0o644)
        try:
            popen = subprocess.Popen(
                command,
                stdin=subprocess.DEVNULL,
                stdout=fd,
                stderr=fd,
                cwd=cwd,
                env=self._env(spec),
                start_new_session=True,
            )
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
        finally:
            os.close(fd)
        try:
            create_time = psutil.Process(popen.pid).create_time()
        except psutil.Error:
            create_time = time.time()
        proc = _Proc(
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

    async def _supervise(self, comp: _Component) -> None:
        """Relaunch a component that crashes, with backoff, until the policy gives up."""
        state = comp.state
        code = await asyncio.shield(comp.proc.exited) if comp.proc is not None else None
        while True:
            if comp.proc is not None:
                # What the leader leaves behind dies with it, as in a container; a relaunch
                # must not run next to the last launch's orphans.
                _signal_group(comp.proc.pid, signal.SIGKILL)
                comp.proc = None
            state.exit_code = code
            if code == 0:
                state.status = Status.EXITED
                self._notify(state)
                return
            who = f"component {state.skill}/{state.component}"
            message = unrunnable(code, who, comp.spec.launch.command)
            delay = None if message else comp.budget.next_delay(time.monotonic(), self._rng)
            if delay is None:
                message = message or give_up_message(who, comp.budget.policy, code)
                logger.warning("%s", message)
                state.status = Status.FAILED
                state.message = message
                self._notify(state)
                return
            state.status = Status.RESTARTING
            self._notify(state)
            await asyncio.sleep(delay)
            try:
                proc = self._launch(comp)
            except RuntimeFailure as exc:
                logger.warning("%s", exc)
                state.message = str(exc)
                code = None
                continue
            state.restarts += 1
            self._notify(state)
            code = await asyncio.shield(proc.exited)

    async def _terminate(self, proc: _Proc, timeout: float) -> int | None:
        """Signal a process group to stop, then kill whatever is left after ``timeout``."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        _signal_group(proc.pid, signal.SIGTERM)
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(asyncio.shield(proc.exited), timeout)
        # Members that outlive the leader get what is left of the timeout, then SIGKILL.
        # Nothing signals a group's end (they are not our children), so look every 50 ms.
        while loop.time() < deadline and _group_alive(proc.pid):  # noqa: ASYNC110
            await asyncio.sleep(0.05)
        _signal_group(proc.pid, signal.SIGKILL)
        return await asyncio.shield(proc.exited)

    async def _rotate_logs_forever(self) -> None:
        """Keep every running component's log under the size limit."""
        while True:
            await asyncio.sleep(self.log_check_interval)
            paths = [self.log_path(*key) for key, comp in self._components.items() if comp.state.status in ACTIVE]
            await asyncio.to_thread(_rotate_all, paths, self.log_max_bytes)


def _adopt(pid: int, create_time: float) -> _Proc | None:
    """Return a handle on a saved process if it still runs and leads its own group."""
    try:
        handle = psutil.Process(pid)
        if not math.isclose(handle.create_time(), create_time, abs_tol=1e-3):
            return None  # the pid now belongs to another process
        if handle.status() == psutil.STATUS_ZOMBIE or os.getpgid(pid) != pid:
            return None
    except (psutil.Error, OSError):
        return None
    return _Proc(
        pid=pid,
        create_time=create_time,
        exited=asyncio.get_running_loop().create_future(),
        handle=handle,
    )


def _signal_group(pgid: int, signum: int) -> bool:
    """Send a signal to a process group; return whether the group still exists."""
    try:
        os.killpg(pgid, signum)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _group_alive(pgid: int) -> bool:
    """Return whether a process group has a member that is not a zombie.

    A zombie leader waits for its parent to reap it: for a group this runtime adopted, that
    parent is another process (an earlier agent, a Celery worker), which may never do so.
    """
    if not _signal_group(pgid, 0):
        return False
    for process in psutil.process_iter(["status"]):
        try:
            if process.info["status"] != psutil.STATUS_ZOMBIE and os.getpgid(process.pid) == pgid:
                return True
        except (psutil.Error, OSError):
            continue
    return False


def _log_failure(fd: int, message: str) -> None:
    """Write why a launch failed into the component's log, where operators look."""
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
        lines = chunk.decode("utf-8", errors="replace").splitlines()[-(count - len(lines)) :] + lines
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


def _measure(
    targets: list[tuple[tuple[str, str], int, dict[tuple[int, float], float]]],
) -> dict[tuple[str, str], tuple[Usage, dict[tuple[int, float], float]]]:
    """Sum CPU seconds, RSS and disk bytes over each component's process tree."""
    children: dict[int, list[int]] = defaultdict(list)
    processes: dict[int, psutil.Process] = {}
    for process in psutil.process_iter(["ppid"]):
        processes[process.pid] = process
        children[process.info["ppid"]].append(process.pid)
    measured: dict[tuple[str, str], tuple[Usage, dict[tuple[int, float], float]]] = {}
    for key, root, seen in targets:
        usage = Usage()
        cpu_now: dict[tuple[int, float], float] = {}
        stack = [root]
        while stack:
            pid = stack.pop()
            process = processes.get(pid)
            if process is None:
                continue
            stack.extend(children.get(pid, ()))
            try:
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
