"""The benchmarks' harness: the flags every benchmark takes, its last line, fleets dealt to client processes."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import _harness as harness

ROOT = Path(__file__).resolve().parent.parent.parent
BENCHMARKS = sorted(p.stem for p in (ROOT / "benchmarks").glob("[!_]*.py") if p.stem != "thesis")


def test_a_benchmark_with_a_cloud_takes_quick_and_its_database_and_redis() -> None:
    parser = harness.arguments("Measure a thing.\n\nHow it is measured.", "short", database="bench_x", redis=7)
    args = parser.parse_args(["--quick"])
    assert args.quick and parser.description == "Measure a thing."
    assert args.database_url == "postgres://postgres@127.0.0.1:5432/bench_x"
    assert args.redis_url == "redis://127.0.0.1:6379/7"


def test_a_benchmark_without_a_cloud_takes_no_urls() -> None:
    args = harness.arguments("Measure a thing.", "short").parse_args([])
    assert not args.quick and not hasattr(args, "database_url") and not hasattr(args, "redis_url")


def test_the_figures_are_one_json_object_on_the_last_line(capsys: pytest.CaptureFixture[str]) -> None:
    print("a table for people")
    harness.report({"routed_over_direct": 0.71, "delivery_ratio": 1.0})
    assert json.loads(capsys.readouterr().out.splitlines()[-1]) == {"routed_over_direct": 0.71, "delivery_ratio": 1.0}


def test_a_fleet_is_dealt_to_client_processes_in_turn() -> None:
    assert harness.shares(list(range(7)), 3) == [[0, 3, 6], [1, 4], [2, 5]]


def _count(index, share, start_event, stop_event, results, offset) -> None:
    start_event.wait(10)
    stop_event.wait(10)
    results.put({"index": index, "sum": sum(share) + offset})


def test_client_processes_start_together_and_report_once_each() -> None:
    clients = harness.Clients(_count, harness.shares(list(range(6)), 2), 100)
    try:
        clients.start_event.set()
        clients.stop_event.set()
        reports = sorted(clients.reports(30), key=lambda r: r["index"])
    finally:
        clients.kill()
    assert reports == [{"index": 0, "sum": 106}, {"index": 1, "sum": 109}]


@pytest.mark.parametrize("name", BENCHMARKS)
def test_every_benchmark_takes_quick(name: str) -> None:
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / f"{name}.py"), "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert "--quick" in done.stdout
