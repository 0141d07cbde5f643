"""daphne's own command line, on uvloop's event loop: what scripts/daphne runs.

daphne runs Twisted on an asyncio loop it creates when ``daphne.server`` is imported, so the
loop's policy is set here, first. Twisted, daphne and the consumers see the same asyncio API;
only the loop's machinery (its callbacks, timers and epoll) runs in C instead of Python. With
thousands of robots connected it is a fifth to a quarter of daphne's CPU (benchmarks/tenk.py
--quick, 3,000 robots, on one machine: 1.76 ms of CPU a robot connecting instead of 2.1, idle 5.2 %
of a core instead of 6.6-7.2, 9,000 points/s ingested at 32 % instead of 38-43 %).
"""

from __future__ import annotations

import asyncio
import sys


def use_uvloop() -> None:
    """Make new event loops uvloop's, where it is installed."""
    try:
        import uvloop
    except ImportError:  # not on this platform: asyncio's own loop serves the same
        return
    asyncio.set_event_loop_policy(uvloop.EventLoopPolicy())


def main() -> None:
    """Run daphne with the arguments given, on uvloop when available."""
    use_uvloop()
    from daphne.cli import CommandLineInterface  # imports daphne.server, which creates the loop

    sys.argv[0] = "daphne"
    CommandLineInterface.entrypoint()


if __name__ == "__main__":
    main()
