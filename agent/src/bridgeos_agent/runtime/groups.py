"""Watch, adopt and signal the process groups the process runtimes launch.

Each component is the leader of its own session, so it is stopped by signalling its whole
group, and it outlives an agent restart (the robot's ProcessRuntime and the cloud's
CloudProcessRuntime both re-adopt it by pid and start time). Exits are seen through pidfds
in the event loop (one file descriptor per process, no thread, no polling), or by one
shared poll where pidfds are not available.
"""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
import math
import os
import subprocess
from dataclasses import dataclass

import psutil

from bridgeos_agent.runtime.base import exit_code

__all__ = ["ExitWatcher", "GroupLeader", "adopt", "group_alive", "signal_group"]

logger = logging.getLogger(__name__)


@dataclass(eq=False, slots=True)
class GroupLeader:
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


class ExitWatcher:
    """Resolve each watched process's exit future: pidfd readiness, or one shared poll."""

    def __init__(self, *, use_pidfd: bool, poll_interval: float) -> None:
        self._use_pidfd = use_pidfd
        self._poll_interval = poll_interval
        self._pidfds: dict[int, GroupLeader] = {}
        self._polled: set[GroupLeader] = set()
        self._poller: asyncio.Task[None] | None = None

    def watch(self, proc: GroupLeader) -> None:
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

    def _forget(self, proc: GroupLeader) -> None:
        """Stop watching a process and release its pidfd."""
        self._polled.discard(proc)
        if proc.pidfd is not None:
            asyncio.get_running_loop().remove_reader(proc.pidfd)
            os.close(proc.pidfd)
            del self._pidfds[proc.pidfd]
            proc.pidfd = None

    def _on_exit(self, proc: GroupLeader) -> None:
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


def adopt(pid: int, create_time: float) -> GroupLeader | None:
    """Return a handle on a saved process if it still runs and leads its own group."""
    try:
        handle = psutil.Process(pid)
        if not math.isclose(handle.create_time(), create_time, abs_tol=1e-3):
            return None  # the pid now belongs to another process
        if handle.status() == psutil.STATUS_ZOMBIE or os.getpgid(pid) != pid:
            return None
    except (psutil.Error, OSError):
        return None
    return GroupLeader(
        pid=pid,
        create_time=create_time,
        exited=asyncio.get_running_loop().create_future(),
        handle=handle,
    )


def signal_group(pgid: int, signum: int) -> bool:
    """Send a signal to a process group; return whether the group still exists."""
    try:
        os.killpg(pgid, signum)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def group_alive(pgid: int) -> bool:
    """Return whether a process group has a member that is not a zombie.

    A zombie leader waits for its parent to reap it: for a group this runtime adopted, that
    parent is another process (an earlier agent, a Celery worker), which may never do so.
    """
    if not signal_group(pgid, 0):
        return False
    for process in psutil.process_iter(["status"]):
        try:
            if process.info["status"] != psutil.STATUS_ZOMBIE and os.getpgid(process.pid) == pgid:
                return True
        except (psutil.Error, OSError):
            continue
    return False
