#!/usr/bin/env python3
"""`make bench`: run every benchmark, then write a report with our figures beside the thesis's.

    .venv/bin/python scripts/bench.py                 # every benchmarks/*.py, full runs
    .venv/bin/python scripts/bench.py --quick         # each with --quick (under a minute each)
    .venv/bin/python scripts/bench.py --only router,vpn --quick
    .venv/bin/python scripts/bench.py --report-only   # rebuild the report from the last results

Each benchmark's progress streams to stderr as it runs; its last stdout line is read as one
JSON object of figures. The report (``.data/bench/report.md``, PNG plots beside it, and
``results.json``) puts every figure ``benchmarks/thesis.py`` knows beside the thesis's
chapter-5 figure and the issue's goal, with a verdict. A benchmark that is missing, fails,
times out or prints no JSON is reported as such; the exit status is non-zero for that only
with ``--strict``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))

from thesis import BENCHMARKS, SKILLS_TABLE_5_2, Figure, verdict  # the one table of reference figures

ROOT = Path(__file__).resolve().parent.parent

# Files in benchmarks/ that are not benchmarks: helpers (_*.py) and the reference table.
NOT_BENCHMARKS = {"thesis"}


@dataclass
class Result:
    """What one benchmark run gave."""

    name: str
    status: str  # ok | failed | timeout | no-json | missing | skipped
    seconds: float = 0.0
    figures: dict[str, Any] = field(default_factory=dict)
    error: str = ""
    returncode: int | None = None

    def to_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def log(message: str) -> None:
    print(f"[bench {time.strftime('%H:%M:%S')}] {message}", file=sys.stderr, flush=True)


def discover(directory: Path) -> list[str]:
    """Return the benchmarks in a directory, by name, sorted."""
    return sorted(p.stem for p in directory.glob("*.py") if not p.stem.startswith("_") and p.stem not in NOT_BENCHMARKS)


def last_json(stdout: str) -> dict[str, Any]:
    """Return the last non-empty line of a benchmark's output as a JSON object, or raise ValueError."""
    lines = [line for line in stdout.splitlines() if line.strip()]
    if not lines:
        raise ValueError("printed nothing on stdout")
    try:
        figures = json.loads(lines[-1])
    except json.JSONDecodeError as exc:
        raise ValueError(f"last line is not JSON ({exc}): {lines[-1][:200]!r}") from None
    if not isinstance(figures, dict):
        raise ValueError(f"last line is JSON but not an object: {lines[-1][:200]!r}")
    return figures


def run_one(script: Path, args: list[str], timeout: float, out_dir: Path) -> Result:
    """Run one benchmark, streaming its output as progress, and read its figures."""
    name = script.stem
    started = time.monotonic()
    stdout_lines: list[str] = []
    log_path = out_dir / f"{name}.log"
    process = subprocess.Popen(
        [sys.executable, str(script), *args],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        errors="replace",
        start_new_session=True,  # a timeout ends the benchmark and everything it started
    )
    with log_path.open("w") as log_file:
        lock = threading.Lock()

        def pump(stream: Any, keep: bool) -> None:
            for line in stream:
                with lock:
                    log_file.write(line)
                    print(f"  [{name}] {line}", end="", file=sys.stderr, flush=True)
                if keep:
                    stdout_lines.append(line)

        pumps = [
            threading.Thread(target=pump, args=(process.stdout, True), daemon=True),
            threading.Thread(target=pump, args=(process.stderr, False), daemon=True),
        ]
        for thread in pumps:
            thread.start()
        try:
            returncode = process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(process.pid, signal.SIGTERM)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()
            for thread in pumps:
                thread.join(timeout=5)
            return Result(name, "timeout", time.monotonic() - started, error=f"no result within {timeout:g} s")
        for thread in pumps:
            thread.join(timeout=30)
    seconds = time.monotonic() - started
    if returncode != 0:
        tail = "".join(stdout_lines[-3:]).strip()[-300:]
        return Result(
            name, "failed", seconds, error=f"exit code {returncode}; see {log_path.name}: {tail}", returncode=returncode
        )
    try:
        figures = last_json("".join(stdout_lines))
    except ValueError as exc:
        return Result(name, "no-json", seconds, error=str(exc), returncode=returncode)
    return Result(name, "ok", seconds, figures=figures, returncode=returncode)


# --------------------------------------------------------------------------- the report


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        return None
    return float(value)


def _fmt(value: Any, unit: str = "") -> str:
    if value is None:
        return "—"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, int | float):
        if value != 0 and (abs(value) >= 1e5 or abs(value) < 1e-3):
            text = f"{value:.3g}"
        elif isinstance(value, int) or float(value).is_integer():
            text = f"{value:,.0f}"
        else:
            text = f"{value:,.4g}"
        return f"{text} {unit}".strip()
    return str(value)[:80]


def rows(name: str, result: Result) -> list[tuple[Figure, float | None, str]]:
    """Return each reference figure of a benchmark with our value and its verdict."""
    out = []
    for figure in BENCHMARKS.get(name, []):
        value = _number(result.figures.get(figure.key)) if result.status == "ok" else None
        out.append((figure, value, verdict(figure, value) if result.status == "ok" else result.status))
    return out


def machine() -> str:
    load = os.getloadavg()
    cpu = "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return (
        f"{platform.node()}: {os.cpu_count()} cores ({cpu}), Python {platform.python_version()}; "
        f"load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f}"
    )


def plot(name: str, table: list[tuple[Figure, float | None, str]], out_dir: Path) -> str | None:
    """Draw our figure over its reference (goal, else thesis) per row; return the PNG's file name."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    bars = []
    for figure, value, text in table:
        reference = figure.goal if figure.goal is not None else figure.thesis
        if value is None or reference is None or reference == 0 or value <= 0 or reference < 0:
            continue
        ratio = value / reference
        good = text.startswith("met") or text.startswith("beats")
        bars.append((f"{figure.label} ({'goal' if figure.goal is not None else 'thesis'})", ratio, good))
    if not bars:
        return None
    fig, ax = plt.subplots(figsize=(8, 0.5 * len(bars) + 1.4))
    labels = [b[0] for b in bars]
    ax.barh(labels, [b[1] for b in bars], color=["#3a9d5d" if b[2] else "#c8553d" for b in bars])
    ax.axvline(1.0, color="black", linewidth=1)
    ax.set_xscale("log")
    ax.set_xlabel("ours / reference (log scale; the line is the reference)")
    ax.set_title(f"{name}: green = goal met or thesis beaten")
    ax.invert_yaxis()
    fig.tight_layout()
    file = f"{name}.png"
    fig.savefig(out_dir / file, dpi=90)
    plt.close(fig)
    return file


def plot_table_5_2(figures: dict[str, Any], out_dir: Path) -> str | None:
    """Draw the Table 5.2 equivalent: per Skill, each change vs all on the robot, ours beside the thesis's."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = ["performance", "cpu", "ram", "network", "power"]
    if not any(_number(figures.get(f"{s}_{k}_pct")) is not None for s in SKILLS_TABLE_5_2 for k in kinds):
        return None
    fig, axes = plt.subplots(1, len(SKILLS_TABLE_5_2), figsize=(12, 3.6), sharey=True)
    for ax, (skill, thesis_row) in zip(axes, SKILLS_TABLE_5_2.items(), strict=True):
        xs = range(len(kinds))
        ours = [_number(figures.get(f"{skill}_{k}_pct")) or 0.0 for k in kinds]
        ax.bar([x - 0.2 for x in xs], [thesis_row[k] for k in kinds], width=0.4, label="thesis", color="#999999")
        ax.bar([x + 0.2 for x in xs], ours, width=0.4, label="ours", color="#3a6ea5")
        ax.axhline(0, color="black", linewidth=0.8)
        ax.set_xticks(list(xs), kinds, rotation=30)
        ax.set_title(skill.replace("_", " "))
    axes[0].set_ylabel("% change vs all on the robot")
    axes[0].legend()
    fig.tight_layout()
    file = "table_5_2.png"
    fig.savefig(out_dir / file, dpi=90)
    plt.close(fig)
    return file


def write_report(results: dict[str, Result], out_dir: Path, mode: str, started: str) -> Path:
    """Write report.md (and its plots) from the results."""
    try:
        import matplotlib  # noqa: F401

        plots = True
    except ImportError:
        plots = False
    lines = [
        "# bridgeOS benchmark report",
        "",
        f"- run: {started}, {mode}",
        f"- machine: {machine()}",
        "- reference: the thesis's chapter-5 figure for the same thing, or the issue's goal "
        "(`benchmarks/thesis.py`); the verdict is against the goal when there is one, and says how we fare "
        "against the thesis.",
        "",
        "| benchmark | status | time | goals met | thesis beaten |",
        "|---|---|---|---|---|",
    ]
    tables = {name: rows(name, result) for name, result in results.items()}
    for name, result in results.items():
        table = tables[name]
        met = sum(1 for _, _, v in table if v.startswith("met"))
        goals = sum(1 for f, value, _ in table if f.goal is not None and value is not None)
        beaten = sum(1 for _, _, v in table if "beats thesis" in v)
        theses = sum(1 for f, value, _ in table if f.thesis is not None and value is not None)
        status = result.status if result.status == "ok" else f"**{result.status}**"
        lines.append(f"| {name} | {status} | {result.seconds:.0f} s | {met}/{goals} | {beaten}/{theses} |")
    for name, result in results.items():
        lines += ["", f"## {name}", ""]
        if result.status != "ok":
            lines += [f"**{result.status}**: {result.error or 'no result'}", ""]
        table = tables[name]
        if table:
            lines += ["| figure | ours | thesis | goal | verdict |", "|---|---|---|---|---|"]
            for figure, value, text in table:
                thesis = (
                    f"{_fmt(figure.thesis, figure.unit)} ({figure.thesis_source})" if figure.thesis is not None else "—"
                )
                goal = (
                    f"{'≤' if figure.better == 'lower' else '≥'} {_fmt(figure.goal, figure.unit)} "
                    f"({figure.goal_source})"
                    if figure.goal is not None
                    else "—"
                )
                lines.append(
                    f"| {figure.label} (`{figure.key}`) | {_fmt(value, figure.unit)} | {thesis} | {goal} | {text} |"
                )
        known = {f.key for f in BENCHMARKS.get(name, [])}
        others = {k: v for k, v in result.figures.items() if k not in known}
        if others:
            lines += ["", "Other figures: " + ", ".join(f"`{k}` {_fmt(v)}" for k, v in others.items())]
        if plots and result.status == "ok" and table:
            file = plot(name, table, out_dir)
            if file:
                lines += ["", f"![{name}]({file})"]
        if name == "usecases" and result.status == "ok":
            lines += ["", "### Table 5.2 equivalent: best combination per Skill vs all on the robot", ""]
            lines += ["| Skill | best | performance | CPU | RAM | network | power |", "|---|---|---|---|---|---|---|"]
            for skill, thesis_row in SKILLS_TABLE_5_2.items():
                ours = [
                    _fmt(_number(result.figures.get(f"{skill}_{k}_pct")), "%")
                    for k in ("performance", "cpu", "ram", "network", "power")
                ]
                best = result.figures.get(f"{skill}_best", "—")
                lines.append(f"| {skill.replace('_', ' ')} (ours) | {best} | " + " | ".join(ours) + " |")
                theirs = [f"{thesis_row[k]:+.2f} %" for k in ("performance", "cpu", "ram", "network", "power")]
                lines.append(
                    f"| {skill.replace('_', ' ')} (thesis) | test {thesis_row['test']} | " + " | ".join(theirs) + " |"
                )
            if plots:
                file = plot_table_5_2(result.figures, out_dir)
                if file:
                    lines += ["", f"![Table 5.2]({file})"]
            matrix = out_dir / "usecases.md"  # every combination, written by benchmarks/usecases.py
            if matrix.exists():
                lines += ["", "### Every location combination (thesis Figure 5.3)", "", matrix.read_text().strip()]
    if not plots:
        lines += ["", "_matplotlib is not installed: no plots (`pip install matplotlib`)._"]
    path = out_dir / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="pass --quick to every benchmark")
    parser.add_argument("--only", default="", help="comma-separated benchmark names to run")
    parser.add_argument("--strict", action="store_true", help="exit 1 if a benchmark is missing or fails")
    parser.add_argument("--timeout", type=float, default=None, help="seconds per benchmark (default 300 quick, 3600)")
    parser.add_argument("--out", type=Path, default=ROOT / ".data" / "bench", help="report directory")
    parser.add_argument("--benchmarks", type=Path, default=ROOT / "benchmarks", help="where the benchmarks are")
    parser.add_argument("--report-only", action="store_true", help="rebuild the report from results.json")
    args = parser.parse_args(argv)
    timeout = args.timeout or (300.0 if args.quick else 3600.0)
    if timeout <= 0:
        parser.error("--timeout must be positive")
    args.out.mkdir(parents=True, exist_ok=True)
    started = time.strftime("%Y-%m-%d %H:%M:%S %Z")
    mode = "quick (--quick)" if args.quick else "full"

    if args.report_only:
        saved = json.loads((args.out / "results.json").read_text())
        results = {name: Result(**data) for name, data in saved["results"].items()}
        report = write_report(results, args.out, saved.get("mode", mode), saved.get("started", started))
        log(f"report: {report}")
        return 0

    found = discover(args.benchmarks)
    wanted = [n.strip() for n in args.only.split(",") if n.strip()] if args.only else None
    names = wanted if wanted is not None else sorted(set(found) | set(BENCHMARKS))
    results: dict[str, Result] = {}
    for index, name in enumerate(names, 1):
        if name not in found:
            log(f"({index}/{len(names)}) {name}: missing (no benchmarks/{name}.py)")
            results[name] = Result(name, "missing", error=f"benchmarks/{name}.py does not exist")
            continue
        log(f"({index}/{len(names)}) {name}: running{' --quick' if args.quick else ''}")
        result = run_one(args.benchmarks / f"{name}.py", ["--quick"] if args.quick else [], timeout, args.out)
        results[name] = result
        log(f"({index}/{len(names)}) {name}: {result.status} in {result.seconds:.1f} s {result.error}".rstrip())
        (args.out / "results.json").write_text(
            json.dumps(
                {"started": started, "mode": mode, "results": {k: v.to_dict() for k, v in results.items()}}, indent=1
            )
        )
    report = write_report(results, args.out, mode, started)
    (args.out / "results.json").write_text(
        json.dumps(
            {"started": started, "mode": mode, "results": {k: v.to_dict() for k, v in results.items()}}, indent=1
        )
    )
    bad = [name for name, r in results.items() if r.status != "ok"]
    log(f"report: {report}" + (f" ({len(bad)} without figures: {', '.join(bad)})" if bad else ""))
    return 1 if args.strict and bad else 0


if __name__ == "__main__":
    sys.exit(main())
