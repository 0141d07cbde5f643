"""Run the life of a supervised component once for every runtime that launches its own.

A runtime that launches and supervises components itself (processes, containers) keeps one
record per component and shares everything but the launching: start waits out a stop in
progress and is idempotent, stop cancels the supervisor before it ends the component (so the
exit it causes is never taken for a crash), and the supervisor relaunches a crashed component
with backoff until its restart policy gives up. A backend says only how to launch, relaunch,
end, wait for and save one component.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import random
import time
from abc import abstractmethod
from collections.abc import Mapping
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, TypeVar

from bridgeos_agent.runtime.base import (
    ACTIVE,
    ComponentSpec,
    ComponentState,
    RestartBudget,
    Runtime,
    RuntimeFailure,
    Status,
    StatusCallback,
    absent,
    check_ids,
    give_up_message,
    unrunnable,
)

__all__ = ["Supervised", "SupervisedRuntime"]

logger = logging.getLogger(__name__)


@dataclass(eq=False, slots=True, kw_only=True)
class Supervised:
    """Hold what a runtime knows and owns for one component it launched or adopted."""

    state: ComponentState
    budget: RestartBudget
    supervisor: asyncio.Task[None] | None = None
    stop_done: asyncio.Future[None] | None = None


R = TypeVar("R", bound=Supervised)


class SupervisedRuntime(Runtime, Generic[R]):
    """Start, stop, supervise and save components; subclasses say how to launch one."""

    def __init__(
        self,
        robot: str,
        *,
        data_dir: Path,
        on_status: StatusCallback | None = None,
        rng: random.Random | None = None,
    ) -> None:
        super().__init__(robot, data_dir=data_dir, on_status=on_status)
        self._records: dict[tuple[str, str], R] = {}
        self._set_aside: list[R] = []  # old copies running beside their new ones (set_aside)
        self._rng = rng  # None: the random module's own generator

    # --- what a backend says -------------------------------------------------------------

    @abstractmethod
    def _new_record(self, spec: ComponentSpec) -> R:
        """Return the record of a component about to be launched (status 'starting')."""

    @abstractmethod
    async def _launch_first(self, rec: R, spec: ComponentSpec) -> None:
        """Launch a component and mark its state running; raise RuntimeFailure saying why not."""

    @abstractmethod
    async def _relaunch(self, rec: R) -> None:
        """Launch a crashed component again and mark it running; raise RuntimeFailure saying why not."""

    @abstractmethod
    def _exited(self, rec: R) -> asyncio.Future[int | None] | None:
        """Return the future resolved with the exit code when the current launch ends, if any."""

    @abstractmethod
    async def _end(self, rec: R, timeout: float) -> None:
        """End the component (SIGTERM, SIGKILL after ``timeout``) and note its exit code."""

    @abstractmethod
    def _command(self, rec: R) -> list[str] | None:
        """Return the command the component was launched with, if known."""

    @abstractmethod
    def _saved(self, rec: R) -> dict[str, Any] | None:
        """Return what else than its ids and restarts get_state keeps of a running component, or None."""

    @abstractmethod
    async def _read_logs(self, skill: str, component: str, tail: int) -> list[str]:
        """Return the last ``tail`` (> 0) lines a component wrote."""

    async def _aside(self, rec: R, aside: bool) -> None:
        """Free the name a running component holds (a container's), or take it back."""

    def _guard(self, rec: R) -> AbstractAsyncContextManager[Any]:
        """Return what serialises the operations on one component (nothing by default)."""
        return contextlib.nullcontext()

    def _reap(self, rec: R) -> None:
        """Clean up after a launch that ended, before the supervisor decides what follows."""

    def _exit_reason(self, rec: R, code: int | None) -> str | None:
        """Say why a launch ended when the runtime knows more than its exit code (e.g. out of memory)."""
        return None

    async def _finished(self, rec: R) -> None:
        """Release what a component held once it ended for good (exited, or given up on)."""

    def _background(self) -> list[asyncio.Task[None]]:
        """Return the runtime's own tasks that close() cancels with the supervisors."""
        return []

    async def _release(self) -> None:
        """Release what the runtime holds once supervision has stopped."""

    # --- the interface -------------------------------------------------------------------

    async def start(self, spec: ComponentSpec) -> ComponentState:
        """Launch a component, or return its state if it is already running."""
        check_ids(spec.skill, spec.component, spec.volumes)
        key = spec.key
        rec = self._records.get(key)
        while rec is not None and rec.stop_done is not None and not rec.stop_done.done():
            await asyncio.shield(rec.stop_done)
            rec = self._records.get(key)
        if rec is not None and rec.state.status in ACTIVE:
            async with self._guard(rec):  # a concurrent start of the same component finishes first
                return dataclasses.replace(rec.state)
        rec = self._new_record(spec)
        self._records[key] = rec
        self._notify(rec.state)
        async with self._guard(rec):
            try:
                await self._launch_first(rec, spec)
            except RuntimeFailure as exc:
                rec.state.status = Status.FAILED
                rec.state.message = str(exc)
                self._notify(rec.state)
                raise
            self._notify(rec.state)
            self._watch(rec)
            return dataclasses.replace(rec.state)

    async def stop(self, skill: str, component: str, timeout: float = 10.0) -> ComponentState:
        """Stop a component: SIGTERM, then SIGKILL after ``timeout`` seconds."""
        check_ids(skill, component)
        rec = self._records.get((skill, component))
        if rec is None:
            return absent(skill, component)
        if rec.stop_done is not None:
            await asyncio.shield(rec.stop_done)
            return dataclasses.replace(rec.state)
        done = rec.stop_done = asyncio.get_running_loop().create_future()
        try:
            async with self._guard(rec):
                if rec.supervisor is not None:
                    # Cancelled first, so the exit our stop causes is never taken for a crash.
                    rec.supervisor.cancel()
                    await asyncio.wait([rec.supervisor])
                await self._end(rec, timeout)
                rec.state.status = Status.STOPPED
                self._notify(rec.state)
        except BaseException:
            rec.stop_done = None  # let a later stop() try again
            raise
        finally:
            done.set_result(None)
        return dataclasses.replace(rec.state)

    async def status(self, skill: str, component: str) -> ComponentState:
        """Return a component's current state (status 'absent' if unknown)."""
        rec = self._records.get((skill, component))
        return absent(skill, component) if rec is None else dataclasses.replace(rec.state)

    async def logs(self, skill: str, component: str, tail: int = 100) -> list[str]:
        """Return the last ``tail`` lines a component wrote to stdout and stderr."""
        check_ids(skill, component)
        if tail <= 0:
            return []
        if self.ring_lines is not None:
            # What the agent captured, in the order it was printed (streams apart in the files).
            lines = await asyncio.to_thread(self.ring_lines, skill, component, tail)
            if lines:
                return lines
        return await self._read_logs(skill, component, tail)

    async def set_aside(self, skill: str, component: str) -> R | None:
        """Keep a running component running but out of its name's way; None when none runs.

        A new version then starts under the name; the copy set aside is no longer supervised,
        reported or saved, and ends with `stop_aside` (or comes back with `restore_aside`).
        """
        rec = self._records.get((skill, component))
        if rec is None or rec.state.status is not Status.RUNNING or rec.stop_done is not None:
            return None
        async with self._guard(rec):
            if rec.supervisor is not None:
                # Its exit (the hand-over's stop, a ROS name clash) is no crash to relaunch.
                rec.supervisor.cancel()
                await asyncio.wait([rec.supervisor])
                rec.supervisor = None
            await self._aside(rec, True)
        del self._records[(skill, component)]
        self._set_aside.append(rec)
        return rec

    async def stop_aside(self, aside: R, timeout: float = 10.0) -> None:
        """End a copy set aside, unreported."""
        async with self._guard(aside):
            await self._end(aside, timeout)
            await self._finished(aside)
        self._set_aside.remove(aside)

    async def restore_aside(self, aside: R) -> None:
        """Put a copy set aside back under its name and supervise it again."""
        async with self._guard(aside):
            await self._aside(aside, False)
        self._set_aside.remove(aside)
        self._records[(aside.state.skill, aside.state.component)] = aside
        self._watch(aside)

    def get_state(self) -> dict[str, Any]:
        """Return what a restarted agent needs to re-adopt the running components."""
        components = []
        for rec in self._records.values():
            state = rec.state
            saved = self._saved(rec) if state.status is Status.RUNNING else None
            if saved is not None:
                ids = {"skill": state.skill, "component": state.component}
                components.append({**ids, **saved, "restarts": state.restarts, "started_at": state.started_at})
        return {"runtime": self.name, "robot": self.robot, "components": components}

    def _foreign(self, state: Mapping[str, Any]) -> bool:
        """Say (and log) whether a saved state belongs to another runtime."""
        if state.get("runtime", self.name) == self.name:
            return False
        logger.warning("ignoring saved state of the %r runtime", state.get("runtime"))
        return True

    async def close(self, stop_components: bool = False) -> None:
        """Stop supervising; stop the components too if asked, else leave them running."""
        if stop_components:
            await asyncio.gather(*(self.stop(*key) for key, rec in self._records.items() if rec.state.status in ACTIVE))
            await asyncio.gather(*(self.stop_aside(rec) for rec in list(self._set_aside)))
        tasks = [rec.supervisor for rec in self._records.values() if rec.supervisor is not None]
        tasks += self._background()
        for task in tasks:
            task.cancel()
        if tasks:
            await asyncio.wait(tasks)
        self._records.clear()
        await self._release()

    # --- supervision ---------------------------------------------------------------------

    def _watch(self, rec: R) -> None:
        """Start the task that supervises a launched or adopted component."""
        state = rec.state
        rec.supervisor = asyncio.create_task(
            self._supervise(rec), name=f"bridgeos-{self.name}-{state.skill}/{state.component}"
        )

    async def _supervise(self, rec: R) -> None:
        """Relaunch a component that crashes, with backoff, until the policy gives up."""
        state = rec.state
        # Awaited here rather than in a helper coroutine: one frame less per supervised component.
        exited = self._exited(rec)
        code = await asyncio.shield(exited) if exited is not None else None
        while True:
            self._reap(rec)
            state.exit_code = code
            reason = self._exit_reason(rec, code)
            if reason is not None:
                # Reported, not only restarted: the cloud sees why in the status's message.
                logger.warning("component %s/%s %s", state.skill, state.component, reason)
                state.message = reason
            if code == 0:
                state.status = Status.EXITED
                self._notify(state)
                await self._finished(rec)
                return
            who = f"component {state.skill}/{state.component}"
            message = unrunnable(code, who, self._command(rec))
            delay = None if message else rec.budget.next_delay(time.monotonic(), self._rng)
            if delay is None:
                message = message or give_up_message(who, rec.budget.policy, code)
                logger.warning("%s", message)
                state.status = Status.FAILED
                state.message = message
                self._notify(state)
                await self._finished(rec)
                return
            state.status = Status.RESTARTING
            self._notify(state)
            await asyncio.sleep(delay)
            try:
                await self._relaunch(rec)
            except RuntimeFailure as exc:
                logger.warning("%s", exc)
                state.message = str(exc)
                code = None
                continue
            state.restarts += 1
            self._notify(state)
            exited = self._exited(rec)
            code = await asyncio.shield(exited) if exited is not None else None
