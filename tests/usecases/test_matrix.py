"""The use-case matrix benchmark: its combinations, its choice of the best, and one real short run."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.usecases import Measurement, best_of, big_figures, big_table, change_pct, main, placements
from bridgeos_agent.skillconfig import load_sample_skill_config

ROOT = Path(__file__).resolve().parent.parent.parent


def row(performance: float | None, power: float, loss: float = 0.0, **placement: str) -> Measurement:
    return Measurement(
        skill="s",
        placement=placement,
        performance=performance,
        cpu_pct=10.0,
        ram_mib=100.0,
        network_kbps=5.0,
        radio_kbps=0.0,
        power_w=power,
        loss_pct=loss,
        init_s=1.0,
    )


@pytest.mark.parametrize(
    ("sample", "count", "fixed"),
    [
        ("people_detection", 4, {"pointcloud": "robot"}),
        ("navigation", 4, {"sim": "robot", "planner": "cloud"}),
        ("mapping", 8, {"sim": "robot"}),
    ],
)
@pytest.mark.parametrize("ros", ["", "_ros2"])
def test_every_combination_the_config_allows_all_on_the_robot_first(
    sample: str, count: int, fixed: dict[str, str], ros: str
) -> None:
    config = load_sample_skill_config(sample + ros)
    combos = placements(config)
    assert len(combos) == count
    assert len({tuple(sorted(c.items())) for c in combos}) == count
    for combo in combos:
        assert set(combo) == set(config.components)
        assert all(combo[c] == where for c, where in fixed.items())
    movable = [c for c, spec in config.components.items() if spec.location == "either"]
    assert all(combos[0][c] == "robot" for c in movable)
    assert all(combos[-1][c] == "cloud" for c in movable)


def test_change_is_positive_when_performance_improves_either_way() -> None:
    assert change_pct(15.0, 10.0) == pytest.approx(50.0)  # higher is better: 15 scans/s against 10
    assert change_pct(50.0, 100.0, higher_is_better=False) == pytest.approx(100.0)  # half the latency
    assert change_pct(200.0, 100.0, higher_is_better=False) == pytest.approx(-50.0)
    assert change_pct(None, 10.0) is None and change_pct(5.0, 0.0) is None


def test_the_best_is_the_cheapest_that_keeps_performance_and_messages() -> None:
    base = row(100.0, power=2.0, a="robot", b="robot")
    cheap_but_slow = row(200.0, power=0.1, a="cloud", b="cloud")  # latency doubled: -50 %
    cheap_but_lossy = row(100.0, power=0.2, loss=20.0, a="robot", b="cloud")
    fine = row(105.0, power=0.5, a="cloud", b="robot")  # -4.8 %: within the 10 % slack
    assert best_of([base, cheap_but_slow, cheap_but_lossy, fine], higher_is_better=False) is fine
    assert best_of([base, cheap_but_slow], higher_is_better=False) is base
    assert fine.label == "cloud: a" and base.label == "all on robot"


def test_thesis_sized_figures_compare_test_4_with_test_1_as_table_5_2_does() -> None:
    robot = row(2000.0, power=3.0, sampler="robot", detector="robot")
    robot.peak_rss_mib = {"router": 125.0, "sampler": 224.0}
    cloud = row(3000.0, power=1.2, sampler="cloud", detector="cloud")
    cloud.cpu_pct, cloud.ram_mib, cloud.radio_kbps = 4.0, 50.0, 7500.0
    cloud.relay_dropped, cloud.relay_delivered, cloud.peak_rss_mib = 1, 3, {"router": 210.0}
    figures = big_figures([robot, cloud], 35.0)
    assert figures["people_detection_35mb_robot_s"] == 2.0 and figures["people_detection_35mb_cloud_s"] == 3.0
    # As the thesis's table: + is slower (processing time) or more (resources).
    assert figures["people_detection_35mb_processing_time_pct"] == pytest.approx(50.0)
    assert figures["people_detection_35mb_cpu_pct"] == pytest.approx(-60.0)
    assert figures["people_detection_35mb_ram_pct"] == pytest.approx(-50.0)
    assert figures["people_detection_35mb_power_pct"] == pytest.approx(-60.0)
    assert figures["people_detection_35mb_router_loss_pct"] == [0.0, 25.0]
    assert figures["people_detection_35mb_router_peak_rss_mib"] == 210.0
    assert figures["people_detection_35mb_node_peak_rss_mib"] == 224.0
    text = big_table([robot, cloud], 35.0, 0.2)
    assert "+64.76 %" in text and "+50.00 %" in text and "1 (25 %)" in text


@pytest.mark.parametrize("bad", [["--cloud-mb", "500"], ["--cloud-mb", "35", "--cloud-rate", "0"], ["--skills="]])
def test_bad_thesis_sized_options_are_refused_clearly(bad: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main(bad)
    assert exit_.value.code == 2 and "error:" in capsys.readouterr().err


@pytest.mark.skipif(os.geteuid() != 0, reason="network namespaces and cgroups need root")
@pytest.mark.parametrize("ros", ["1", "2"])
def test_a_short_real_run_prints_the_table_5_2_figures(tmp_path: Path, ros: str) -> None:
    out = tmp_path / "matrix.md"
    domain = os.environ.get("BRIDGEOS_TEST_ROS2_DOMAIN", "46")  # --ros 2: a DDS domain of the tests' own
    bench = [sys.executable, str(ROOT / "benchmarks" / "usecases.py"), "--quick", "--skills", "mapping"]
    done = subprocess.run(
        [*bench, "--out", str(out), "--ros", ros, "--ros-domain", domain],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    figures = json.loads(done.stdout.strip().splitlines()[-1])
    assert figures["combinations"] == 2 and figures["ros"] == int(ros)
    assert figures["mapping_best"] in ("all on robot", "cloud: controller, mapping, odometry")
    for key in ("performance", "cpu", "ram", "network", "power"):
        assert isinstance(figures[f"mapping_{key}_pct"], (int, float))
    assert 0.9 <= figures["delivery_ratio"] <= 1.0
    assert 0 < figures["skill_init_s"] < 60
    table = out.read_text()
    assert "| all on robot" in table and "cloud: controller, mapping, odometry" in table
    # Both runs mapped scans: a number in the performance column of each row.
    rows = [line for line in table.splitlines() if line.startswith("| ") and "combination" not in line]
    assert len(rows) == 2 and all(float(r.split("|")[2]) > 0 for r in rows)
