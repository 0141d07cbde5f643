"""How fast `bridgeos` starts: the wall time of `bridgeos --help`, the benchmark's `cli_start_ms`."""

from __future__ import annotations

import shutil
import statistics
import subprocess
import time
from collections.abc import Sequence


def cli_start_ms(command: Sequence[str] | None = None, *, runs: int = 5) -> float:
    """Return the median wall time, in milliseconds, of running ``bridgeos --help`` (or ``command``) to its end."""
    if command is None:
        script = shutil.which("bridgeos")
        if script is None:
            raise FileNotFoundError("no `bridgeos` on PATH: install ./cli (make install does)")
        command = [script, "--help"]
    times = []
    for _ in range(runs):
        started = time.perf_counter()
        subprocess.run(list(command), check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        times.append((time.perf_counter() - started) * 1000)
    return round(statistics.median(times), 1)
