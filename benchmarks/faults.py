"""The fault suite: break every real part on purpose, with many robots, and report what survived.

Each scenario (benchmarks/chaos/) injects one fault against real daphne, Celery, Redis,
PostgreSQL, agents and links, and counts what was sent, stored, lost and duplicated and how
long recovery took. Prints one table, then one JSON object as the last line.

    python benchmarks/faults.py --quick            # every scenario, each under a minute
    python benchmarks/faults.py --only link,hog    # some of them
    make chaos                                     # every scenario in full
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
import traceback
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from benchmarks._common import ROOT, log
from benchmarks.chaos import SCENARIOS, Outcome, load, summary

COLUMNS = ("scenario", "injected", "sent", "stored", "lost", "duplicated", "recover_s", "passed")


def table(outcomes: list[Outcome]) -> str:
    """Render the outcomes as a Markdown table, one row per injected fault."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for outcome in outcomes:
        row = outcome.row()
        cells = [
            "" if row[c] is None else ("yes" if row[c] is True else "NO" if row[c] is False else str(row[c]))
            for c in COLUMNS
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run(names: list[str], quick: bool) -> list[Outcome]:
    """Play the named scenarios in order; a scenario that raises counts as one failed outcome."""
    outcomes: list[Outcome] = []
    for name in names:
        module = load(name)
        started = time.monotonic()
        log(f"scenario {name}: {module.INJECTS}")
        try:
            got = module.run(quick)
        except Exception as exc:
            traceback.print_exc()
            got = [Outcome(scenario=name, injected=module.INJECTS, detail=f"raised {exc!r}")]
        for outcome in got:
            log(f"  {outcome.injected}: {'passed' if outcome.passed else 'FAILED'} {outcome.detail}")
        log(f"scenario {name}: {time.monotonic() - started:.1f} s")
        outcomes.extend(got)
    return outcomes


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="each scenario in its short form (under a minute)")
    parser.add_argument("--only", default="", help=f"comma-separated scenarios (of {', '.join(SCENARIOS)})")
    args = parser.parse_args()
    names = [n.strip() for n in args.only.split(",") if n.strip()] or list(SCENARIOS)
    unknown = [n for n in names if n not in SCENARIOS]
    if unknown:
        parser.error(f"unknown scenario(s) {', '.join(unknown)}; known: {', '.join(SCENARIOS)}")
    outcomes = run(names, args.quick)
    print(table(outcomes), flush=True)
    print(json.dumps(summary(outcomes)), flush=True)


if __name__ == "__main__":
    os.chdir(ROOT)
    main()
