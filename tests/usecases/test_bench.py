"""`make bench`'s runner and report, on canned benchmarks that print known figures.

The benchmarks here are tiny real scripts run by scripts/bench.py as subprocesses: one
good, one failing, one printing no JSON, one hanging, plus helpers that must not run.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from benchmarks.thesis import BENCHMARKS, Figure, verdict

ROOT = Path(__file__).resolve().parent.parent.parent
PNG = b"\x89PNG\r\n\x1a\n"

ROUTER = """
import json, sys
print("mapping topics...", file=sys.stderr, flush=True)
print("topic map 1.2 ms (thesis 443 ms)")
print(json.dumps({"topic_map_ms": 1.2, "max_topics": 20000, "routed_over_direct": 0.5, "delivery_ratio": 1.0,
                  "added_latency_p50_ms": 0.3, "router_mb": 3.1, "kb_per_topic": 1.6, "quick": "--quick" in sys.argv}))
"""

USECASES = """
import json
figures = {"delivery_ratio": 0.999, "skill_init_s": 2.5, "people_detection_best": "test 4"}
for skill in ("people_detection", "navigation", "mapping"):
    for kind, value in (("performance", 10.0), ("cpu", -90.0), ("ram", -50.0), ("network", 20.0), ("power", -70.0)):
        figures[f"{skill}_{kind}_pct"] = value
print(json.dumps(figures))
"""

CANNED = {
    "router.py": ROUTER,
    "usecases.py": USECASES,
    "vpn.py": "import sys\nprint('tunnel failed', file=sys.stderr)\nsys.exit(3)\n",
    "broken.py": "print('all done, no figures')\n",
    "hangs.py": "import time\nprint('{}')\ntime.sleep(600)\n",
    "_helper.py": "raise SystemExit('helpers are not benchmarks')\n",
    "thesis.py": "raise SystemExit('the reference table is not a benchmark')\n",
}


@pytest.fixture
def canned(tmp_path: Path) -> Path:
    directory = tmp_path / "benchmarks"
    directory.mkdir()
    for name, code in CANNED.items():
        (directory / name).write_text(textwrap.dedent(code))
    return directory


def bench(canned: Path, out: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "bench.py"), "--benchmarks", str(canned), "--out", str(out), *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_the_report_sets_every_figure_beside_the_thesis_and_says_what_went_wrong(canned: Path, tmp_path: Path) -> None:
    out = tmp_path / "report"
    done = bench(canned, out, "--quick", "--timeout", "10")

    assert done.returncode == 0, done.stderr  # failures are reported, not fatal, without --strict
    assert "  [router] mapping topics..." in done.stderr  # progress streams through
    results = json.loads((out / "results.json").read_text())["results"]
    assert results["router"]["status"] == "ok" and results["router"]["figures"]["quick"] is True
    assert results["vpn"]["status"] == "failed" and "exit code 3" in results["vpn"]["error"]
    assert results["broken"]["status"] == "no-json"
    assert results["hangs"]["status"] == "timeout"
    assert results["cloud_components"]["status"] == "missing"
    assert "_helper" not in results and "thesis" not in results

    report = (out / "report.md").read_text()
    assert (
        "| time to map a topic (`topic_map_ms`) | 1.2 ms | 443 ms (Fig. 5.9: 443 ± 20 ms) | ≤ 10 ms (issue 7) | met; beats thesis |"
        in report
    )
    assert "| routed / direct rospy throughput (`routed_over_direct`) | 0.5 | — | ≥ 0.6 (issue 7) | MISSED |" in report
    assert (
        "**failed**: exit code 3" in report and "**missing**: benchmarks/cloud_components.py does not exist" in report
    )
    assert "**timeout**" in report and "**no-json**" in report
    assert "Table 5.2 equivalent" in report
    assert "| people detection (thesis) | test 4 | +64.76 % | -88.32 % |" in report
    assert "| people detection (ours) | test 4 | 10 % | -90 % |" in report
    for png in ("router.png", "usecases.png", "table_5_2.png"):
        assert (out / png).read_bytes().startswith(PNG), png
        assert f"]({png})" in report


def test_only_and_strict_and_report_only(canned: Path, tmp_path: Path) -> None:
    out = tmp_path / "report"
    good = bench(canned, out, "--only", "router", "--strict")
    assert good.returncode == 0, good.stderr
    assert set(json.loads((out / "results.json").read_text())["results"]) == {"router"}

    failing = bench(canned, out, "--only", "router,vpn", "--strict")
    assert failing.returncode == 1

    (out / "report.md").unlink()
    rebuilt = bench(canned, out, "--report-only")
    assert rebuilt.returncode == 0 and "## vpn" in (out / "report.md").read_text()


@pytest.mark.parametrize(
    ("figure", "value", "expected"),
    [
        (Figure("x", "x", thesis=443, goal=10), 5, "met; beats thesis"),
        (Figure("x", "x", thesis=443, goal=10), 100, "MISSED; beats thesis"),
        (Figure("x", "x", thesis=5000, goal=20000, better="higher"), 4000, "MISSED; thesis better"),
        (Figure("x", "x", thesis=0.9842, better="higher"), 0.9842, "equals thesis"),
        (Figure("x", "x"), 3, "no reference"),
        (Figure("x", "x", goal=1), None, "not measured"),
    ],
)
def test_verdicts(figure: Figure, value: float | None, expected: str) -> None:
    assert verdict(figure, value) == expected


def test_the_reference_table_names_each_key_once_per_benchmark() -> None:
    for name, figures in BENCHMARKS.items():
        keys = [f.key for f in figures]
        assert len(keys) == len(set(keys)), name
        assert all(f.better in ("lower", "higher") for f in figures)
    assert {"router", "cloud_components", "vpn", "offloading_quality", "usecases"} <= set(BENCHMARKS)
