"""The robot's component logs: capture every component's output into its ring, ship it, answer for it.

Every ``POLL`` seconds one pass, in a thread, reads what each component printed since its ring's
saved position (the runtime says where: ``Runtime.log_sources``) and appends it to the ring.
The shipper sends the rings' new lines to the cloud; ``component_logs_get`` and a crash report's
last lines are answered from the rings.
"""

from __future__ import annotations

import asyncio
import logging
import threading
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bridgeos_agent import protocol
from bridgeos_agent.logonce import LogOnce
from bridgeos_agent.logs.capture import FileTail, LogSource
from bridgeos_agent.logs.ring import RingLine, Rings
from bridgeos_agent.logs.shipper import LogShipper, frame_data
from bridgeos_agent.robotconfig import LogsPolicy

if TYPE_CHECKING:
    from bridgeos_agent.runtime.base import Runtime
    from bridgeos_agent.session import Session

__all__ = ["POLL", "ComponentLogService", "line_dicts"]

logger = logging.getLogger("bridgeos_agent")

POLL = 0.1  # seconds between capture passes: a printed line reaches its ring within this
ENDED_WAIT = 1.0  # how long a crash report waits for a container's log stream to reach its end


def line_dicts(lines: list[RingLine]) -> list[dict[str, Any]]:
    """Return ring lines as LogLine dicts."""
    return frame_data("", "", lines)["lines"]


class ComponentLogService:
    """Own the rings, the capture pass and the shipper of one robot."""

    def __init__(
        self,
        data_dir: Path,
        runtime: Runtime,
        session: Session,
        policy: LogsPolicy | None = None,
        *,
        poll: float = POLL,
    ) -> None:
        policy = policy or LogsPolicy()
        self.runtime = runtime
        self.rings = Rings(data_dir, max_bytes=policy.ring_bytes)
        self.shipper = LogShipper(
            self.rings, session, lines_per_s=policy.rate_lines_per_s, bytes_per_s=policy.rate_bytes_per_s
        )
        self.policy = policy
        self.poll = poll
        self._capturing = threading.Lock()  # one pass at a time: two would read the same bytes twice
        self._failures = LogOnce(logger, "capturing the components' output")
        runtime.ring_lines = self.tail_text

    def apply(self, policy: LogsPolicy) -> None:
        """Use a robot config's ``logs`` section."""
        self.policy = policy
        self.rings.resize(policy.ring_bytes)
        self.shipper.lines.set_rate(policy.rate_lines_per_s)
        self.shipper.bytes.set_rate(policy.rate_bytes_per_s)
        self.shipper.enabled = policy.enabled

    async def run(self) -> None:
        """Capture and ship until cancelled (with ``enabled`` off the rings still fill; nothing is shipped)."""
        shipping = asyncio.ensure_future(self.shipper.run())
        try:
            while True:
                await asyncio.sleep(self.poll)
                await self.capture()
        finally:
            shipping.cancel()
            await asyncio.gather(shipping, return_exceptions=True)

    async def capture(self, only: tuple[str, str] | None = None, *, final: bool = False) -> int:
        """Read every component's new output into its ring (in a thread); return the lines taken."""
        # Asked on the loop: the runtime's records change there.
        sources = {key: source for key, source in self.runtime.log_sources().items() if only in (None, key)}
        try:
            taken = await asyncio.to_thread(self._capture, sources, final)
        except Exception as exc:  # a runtime's source failing in its own way: said once, tried next pass
            self._failures.failed(exc)
            return 0
        self._failures.worked()
        if taken:
            self.shipper.wake.set()
        return taken

    def _capture(self, sources: dict[tuple[str, str], LogSource], final: bool) -> int:
        taken = 0
        with self._capturing:
            for key, source in sources.items():
                ring = self.rings.get(*key)
                assert ring is not None
                if isinstance(source, FileTail):
                    source.keep_bytes = ring.max_bytes
                found, position = source.read(ring.source or None, final=final)
                if isinstance(source, FileTail):
                    ring.skip(source.take_skipped())  # before this pass's lines: they were printed after
                if found or position != ring.source:
                    ring.append(found, position)
                taken += len(found)
        return taken

    # --- answers from the rings ------------------------------------------------------------

    async def last_lines(self, skill: str, component: str, count: int = protocol.CRASH_LOG_LINES) -> list[dict]:
        """Return a component's last lines as LogLine dicts, after reading what it printed last."""
        ended = getattr(self.runtime.log_sources().get((skill, component)), "ended", None)
        if ended is not None:  # a container's log stream: its last lines come when the stream ends
            await asyncio.to_thread(ended.wait, ENDED_WAIT)
        await self.capture((skill, component), final=True)
        ring = self.rings.get(skill, component, create=False)
        return line_dicts(await asyncio.to_thread(ring.last, count)) if ring is not None else []

    async def lines_after(self, skill: str, component: str, after: int, limit: int) -> dict[str, Any]:
        """Return the data of a ``component_logs`` reply: the ring's lines after ``after``."""
        ring = self.rings.get(skill, component, create=False)
        if ring is None:
            return frame_data(skill, component, [])
        budget = protocol.MAX_FRAME_BYTES // 2
        lines = await asyncio.to_thread(ring.lines_after, after, limit, budget)
        # Asked from the start of what the ring holds: the lines before it are gone, counted.
        dropped = max(0, lines[0][0] - after - 1) if lines else 0
        return frame_data(skill, component, lines, dropped)

    def tail_text(self, skill: str, component: str, count: int) -> list[str]:
        """Return the text of a component's last lines (what ``Runtime.logs`` shows)."""
        ring = self.rings.get(skill, component, create=False)
        return [line[4] for line in ring.last(count)] if ring is not None else []
