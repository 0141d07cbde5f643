"""api_load's --profile: record daphne with py-spy during the load and log its hottest functions."""

from __future__ import annotations

import subprocess
import sys
from collections import Counter
from pathlib import Path

from _common import ROOT, log


def spawn_profiler(pid: int, seconds: float, out: str) -> subprocess.Popen:
    """Start py-spy recording a process for ``seconds`` into ``out`` (raw, collapsed stacks)."""
    py_spy = Path(sys.executable).parent / "py-spy"
    cmd = [str(py_spy), "record", "-d", str(int(seconds)), "-r", "50", "-f", "raw", "-o", out, "--pid", str(pid)]
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def frame_name(frame: str) -> str:
    """Turn py-spy's `func (path/to/file.py:123)` into `to/file.py:func`."""
    func, sep, where = frame.partition(" (")
    if not sep:
        return frame
    path = where.rsplit(":", 1)[0]
    for marker in ("site-packages/", str(ROOT) + "/"):
        path = path.split(marker, 1)[-1]
    return f"{path}:{func}"


IDLE_FRAMES = ("EpollSelector.select", "Condition.wait", "thread.py:_worker", "Thread._wait_for_tstate_lock")
WRAPPER_PREFIXES = (
    "threading.py",
    "concurrent/",
    "asgiref/",
    "asyncio/",
    "selectors.py",
    "django/core/handlers/",
    "django/utils/deprecation.py",
    "whitenoise/",
    "django/views/",
    "daphne/",
    "twisted/",
    "channels/",
)


def summarise_profile(path: str, top: int = 15) -> None:
    """Log the hottest functions of a py-spy raw (collapsed) profile, as shares of busy samples."""
    own: Counter[str] = Counter()
    inclusive: Counter[str] = Counter()
    total = idle = 0
    for line in Path(path).read_text().splitlines():
        stack, _, count = line.rpartition(" ")
        if not stack or not count.isdigit():
            continue
        frames = [frame_name(f) for f in stack.split(";")]
        if frames[-1].endswith(IDLE_FRAMES):
            idle += int(count)
            continue
        total += int(count)
        own[frames[-1]] += int(count)
        for frame in set(frames):
            inclusive[frame] += int(count)
    if not total:
        log("py-spy: no busy samples")
        return
    log(f"py-spy: {total} busy samples ({idle} idle left out) in {path}; self time:")
    for frame, n in own.most_common(top):
        log(f"  {100 * n / total:5.1f}%  {frame}")
    log("py-spy: inclusive time (request wrappers left out):")
    hot = [(f, n) for f, n in inclusive.most_common() if not f.startswith(WRAPPER_PREFIXES)]
    for frame, n in hot[: 2 * top]:
        log(f"  {100 * n / total:5.1f}%  {frame}")
