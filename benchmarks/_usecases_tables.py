"""usecases.py's verdicts and tables: the best combination per Skill, the matrix and Table 5.2 beside ours."""

from __future__ import annotations

from _usecases_run import SKILLS, Measurement

PERFORMANCE_SLACK = 0.10  # a best combination may be this much slower than all on the robot
MAX_LOSS_PCT = 5.0
# Thesis Table 5.2, People Detection: its best combination (Test 4, sampler and detector in the
# cloud) against all on the robot. "Performance" is the change of the mean processing time of a
# pointcloud (the text: "a dramatic increase in the mean processing time"), so + is slower.
THESIS_TABLE_5_2 = {"processing_time": 64.76, "cpu": -88.32, "ram": -45.85, "network": 137.21, "power": -63.10}


def change_pct(value: float | None, base: float | None, higher_is_better: bool = True) -> float | None:
    """Return the change from the base in percent; for performance, positive means better."""
    if value is None or base is None or base == 0:
        return None
    if higher_is_better:
        return 100 * (value - base) / base
    return 100 * (base / value - 1) if value else None


def best_of(rows: list[Measurement], higher_is_better: bool) -> Measurement:
    """Return the lowest-power combination that keeps performance within the slack, arriving messages."""
    base = rows[0]
    fine = []
    for row in rows:
        change = change_pct(row.performance, base.performance, higher_is_better)
        if change is not None and change >= -100 * PERFORMANCE_SLACK and row.loss_pct <= MAX_LOSS_PCT:
            fine.append(row)
    return min(fine or [base], key=lambda r: r.power_w)


def table(skill: str, rows: list[Measurement]) -> str:
    """Return one Skill's combinations as a markdown table (thesis Figure 5.3's rows)."""
    best = best_of(rows, SKILLS[skill].higher_is_better)
    lines = [
        f"### {skill.replace('_', ' ')}: performance is {SKILLS[skill].performance}",
        "",
        "| combination | performance | robot CPU % | robot RAM MiB | robot network kB/s | radio kB/s "
        "| power W (eq. 4.1) | loss % | first result s |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row in rows:
        perf = f"{row.performance:.3g}" if row.performance is not None else "—"
        init = f"{row.init_s:.2f}" if row.init_s is not None else "—"
        label = f"**{row.label}** (best)" if row is best else row.label
        lines.append(
            f"| {label} | {perf} | {row.cpu_pct:.1f} | {row.ram_mib:.1f} | {row.network_kbps:.1f} "
            f"| {row.radio_kbps:.1f} | {row.power_w:.2f} | {row.loss_pct:.2f} | {init} |"
        )
    return "\n".join(lines)


def big_table(rows: list[Measurement], megabytes: float, rate: float) -> str:
    """Return the thesis-sized run as a table, then Table 5.2's row beside ours (Test 4 against Test 1)."""
    processes = sorted({name for row in rows for name in row.peak_rss_mib})
    lines = [
        f"### people detection with {megabytes:g} MB clouds at {rate:g} Hz, relayed by the Skill Router",
        "",
        "| combination | cloud→detection s (median) | detections | robot CPU % | robot RAM MiB | robot network kB/s "
        "| radio kB/s | power W | router dropped (of relayed) | "
        + " | ".join(f"peak RSS {p} MiB" for p in processes)
        + " |",
        "|---" * (9 + len(processes)) + "|",
    ]
    for row in rows:
        perf = f"{row.performance / 1000:.2f}" if row.performance is not None else "—"
        peaks = " | ".join(f"{row.peak_rss_mib[p]:.0f}" if p in row.peak_rss_mib else "—" for p in processes)
        lines.append(
            f"| {row.label} | {perf} | {row.results} | {row.cpu_pct:.1f} | {row.ram_mib:.1f} | {row.network_kbps:.1f} "
            f"| {row.radio_kbps:.1f} | {row.power_w:.2f} | {row.relay_dropped} ({row.relay_loss_pct:.0f} %) | {peaks} |"
        )
    ours = table_5_2_changes(rows)
    lines += [
        "",
        "Table 5.2 (people detection, Test 4 = sampler and detector in the cloud, against Test 1 = all on the robot):",
        "",
        "| change vs all on the robot | processing time | CPU | RAM | network IO | power |",
        "|---|---|---|---|---|---|",
        "| thesis (T2.Micro robot, 220 Mb LAN) | "
        + " | ".join(f"{THESIS_TABLE_5_2[k]:+.2f} %" for k in THESIS_TABLE_5_2)
        + " |",
        "| this run | "
        + " | ".join(f"{ours[k]:+.2f} %" if ours[k] is not None else "—" for k in THESIS_TABLE_5_2)
        + " |",
        "",
        f"Network IO here is everything the robot's side sent (loopback, the router's relays included, plus the "
        f"link); the link alone went from {rows[0].radio_kbps:.0f} to {rows[-1].radio_kbps:.0f} kB/s.",
    ]
    return "\n".join(lines)


def table_5_2_changes(rows: list[Measurement]) -> dict[str, float | None]:
    """Return Table 5.2's changes (%) of all in the cloud against all on the robot (+ is more)."""
    base, test4 = rows[0], rows[-1]
    return {
        "processing_time": rounded(change_pct(test4.performance, base.performance)),
        "cpu": rounded(change_pct(test4.cpu_pct, base.cpu_pct)),
        "ram": rounded(change_pct(test4.ram_mib, base.ram_mib)),
        "network": rounded(change_pct(test4.network_kbps, base.network_kbps)),
        "power": rounded(change_pct(test4.power_w, base.power_w)),
    }


def big_figures(rows: list[Measurement], megabytes: float) -> dict[str, object]:
    """Return the thesis-sized run's last-line figures (``people_detection_<MB>mb_*``)."""
    key = f"people_detection_{megabytes:g}mb".replace(".", "_")
    base, cloud = rows[0], rows[-1]
    figures: dict[str, object] = {
        f"{key}_robot_s": rounded(base.performance / 1000 if base.performance is not None else None),
        f"{key}_cloud_s": rounded(cloud.performance / 1000 if cloud.performance is not None else None),
        f"{key}_detections": [row.results for row in rows],
        f"{key}_router_dropped": [row.relay_dropped for row in rows],
        f"{key}_router_loss_pct": [round(row.relay_loss_pct, 2) for row in rows],
        f"{key}_router_peak_rss_mib": rounded(max((r.peak_rss_mib.get("router", 0.0) for r in rows), default=None)),
        f"{key}_node_peak_rss_mib": rounded(
            max((v for r in rows for k, v in r.peak_rss_mib.items() if k != "router"), default=None)
        ),
    }
    for name, change in table_5_2_changes(rows).items():
        figures[f"{key}_{name}_pct"] = change
    return figures


def rounded(value: float | None) -> float | None:
    """Round a figure to two places; None stays None."""
    return round(value, 2) if value is not None else None
