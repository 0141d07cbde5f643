"""Own and restart the long-running tasks of one Skill (its Skill Manager and Skill Router)."""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field

from bridgeos_agent.runtime.base import RestartBudget, RestartPolicy

__all__ = ["SkillPlugin", "SkillSupervisor"]

logger = logging.getLogger(__name__)

# A plug-in is an async callable run for the life of a Skill, e.g. its manager or router.
SkillPlugin = Callable[["SkillSupervisor"], Awaitable[None]]


@dataclass
class _Task:
    name: str
    plugin: SkillPlugin
    budget: RestartBudget
    task: asyncio.Task | None = None
    restarts: int = 0
    failed: bool = False


@dataclass
class SkillSupervisor:
    """Run a Skill's plug-ins; a crashed plug-in restarts with backoff, not the agent."""

    skill: str
    policy: RestartPolicy = field(default_factory=RestartPolicy)
    on_failure: Callable[[str, str], None] | None = None
    context: dict[str, object] = field(default_factory=dict)
    # What the controller tells the Skill (e.g. "connection_lost", "connection_established"),
    # for its manager to read; bounded so a Skill that never reads cannot grow it.
    events: asyncio.Queue[str] = field(default_factory=lambda: asyncio.Queue(maxsize=100))
    _tasks: dict[str, _Task] = field(default_factory=dict)
    _ready: dict[str, asyncio.Event] = field(default_factory=dict)
    _closed: bool = False

    def start(self, name: str, plugin: SkillPlugin) -> None:
        """Run ``plugin`` under supervision as ``name``."""
        if name in self._tasks:
            raise ValueError(f"skill {self.skill}: a task named {name!r} runs already")
        entry = _Task(name, plugin, RestartBudget(self.policy))
        self._tasks[name] = entry
        self._ready[name] = asyncio.Event()
        entry.task = asyncio.get_running_loop().create_task(self._run(entry), name=f"{self.skill}:{name}")

    def mark_ready(self, name: str) -> None:
        """Say a plug-in is ready for the Skill's components (e.g. its API listens)."""
        self._ready[name].set()

    async def wait_ready(self, timeout: float) -> list[str]:
        """Wait until every plug-in is ready (or has ended); return those still not ready."""
        waits = [asyncio.ensure_future(event.wait()) for event in self._ready.values()]
        if waits:
            _, pending = await asyncio.wait(waits, timeout=timeout)
            for wait in pending:
                wait.cancel()
        return [name for name, event in self._ready.items() if not event.is_set()]

    async def _run(self, entry: _Task) -> None:
        try:
            await self._supervise(entry)
        finally:
            self._ready[entry.name].set()  # an ended plug-in holds nobody back

    async def _supervise(self, entry: _Task) -> None:
        while not self._closed:
            try:
                await entry.plugin(self)
                return  # a plug-in that returns has finished its work
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                delay = entry.budget.next_delay(time.monotonic())
                if delay is None:
                    entry.failed = True
                    logger.error("skill %s: %s failed for good: %s", self.skill, entry.name, exc)
                    if self.on_failure is not None:
                        self.on_failure(entry.name, f"{entry.name} crashed too often: {exc}")
                    return
                entry.restarts += 1
                logger.warning("skill %s: %s crashed (%s); restarting in %.1f s", self.skill, entry.name, exc, delay)
                await asyncio.sleep(delay)

    def notify(self, event: str) -> None:
        """Tell the Skill's plug-ins something; the oldest unread notice makes room if full."""
        if self.events.full():
            self.events.get_nowait()
        self.events.put_nowait(event)

    def restarts(self, name: str) -> int:
        """Return how often a plug-in was restarted."""
        return self._tasks[name].restarts

    def running(self, name: str) -> bool:
        """Tell whether a plug-in is still running."""
        entry = self._tasks.get(name)
        return entry is not None and entry.task is not None and not entry.task.done()

    async def close(self) -> None:
        """Cancel every plug-in and wait for them to end."""
        self._closed = True
        tasks = [entry.task for entry in self._tasks.values() if entry.task is not None]
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
