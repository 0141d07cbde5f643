"""The figures our benchmarks are judged by: the thesis's chapter 5 and the issues' goals, in one place.

``scripts/bench.py`` reads each benchmark's last-line JSON and puts every key listed here
beside the thesis's figure for the same thing (``thesis``) and the goal its issue set
(``goal``), with a verdict from :func:`verdict`. This is a table, not a benchmark:
``make bench`` does not run it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

__all__ = ["BENCHMARKS", "SKILLS_TABLE_5_2", "Figure", "verdict"]


@dataclass(frozen=True)
class Figure:
    """One figure a benchmark prints, and what it is compared with."""

    key: str
    label: str
    unit: str = ""
    thesis: float | None = None  # the thesis's figure (or the measurement) for the same thing
    thesis_source: str = ""
    goal: float | None = None  # the goal
    goal_source: str = ""
    better: Literal["lower", "higher"] = "lower"


def verdict(figure: Figure, value: float | None) -> str:
    """Say how a value fares: against the goal when there is one, and against the thesis."""
    if value is None:
        return "not measured"

    def fares(target: float) -> bool:
        return value <= target if figure.better == "lower" else value >= target

    parts = []
    if figure.goal is not None:
        parts.append("met" if fares(figure.goal) else "MISSED")
    if figure.thesis is not None:
        if value == figure.thesis:
            parts.append("equals thesis")
        else:
            parts.append("beats thesis" if fares(figure.thesis) else "thesis better")
    return "; ".join(parts) or "no reference"


def _f(key: str, label: str, unit: str = "", **kw: object) -> Figure:
    return Figure(key, label, unit, **kw)  # type: ignore[arg-type]


# Thesis Table 5.2: the best location combination per Skill against all on the robot (% change).
SKILLS_TABLE_5_2 = {
    "people_detection": {
        "test": 4,
        "performance": 64.76,
        "cpu": -88.32,
        "ram": -45.85,
        "network": 137.21,
        "power": -63.10,
    },
    "navigation": {"test": 2, "performance": 2.11, "cpu": -83.99, "ram": -5.30, "network": 2.98, "power": -72.33},
    "mapping": {"test": 8, "performance": -8.18, "cpu": -92.78, "ram": -67.87, "network": -80.85, "power": -87.93},
}

_T52 = "Table 5.2"


def _usecase_figures() -> list[Figure]:
    figures = [
        _f(
            "delivery_ratio",
            "ROS messages delivered",
            "",
            thesis=0.9842,
            thesis_source="§5.3.1: 98.42 ± 0.63 %",
            goal=1.0,
            goal_source="issue 7",
            better="higher",
        ),
        _f("skill_init_s", "Skill initialisation", "s", thesis=5.0, thesis_source="§5.3.1: under 5 s"),
    ]
    for skill, row in SKILLS_TABLE_5_2.items():
        name = skill.replace("_", " ")
        for what, unit in (("performance", "%"), ("cpu", "%"), ("ram", "%"), ("network", "%"), ("power", "%")):
            figures.append(
                _f(
                    f"{skill}_{what}_pct",
                    f"{name}: best combination's {what} vs all on robot",
                    unit,
                    thesis=row[what],
                    thesis_source=f"{_T52} (test {row['test']})",
                )
            )
    return figures


BENCHMARKS: dict[str, list[Figure]] = {
    "skills_startup": [
        _f("seq_init_s", "Skill init, sequential", "s", thesis=5.26, thesis_source="Fig. 5.6: 5.26 ± 0.61 s"),
        _f("parallel_init_s", "Skill init, parallel", "s", thesis=2.19, thesis_source="Fig. 5.6: 2.19 ± 0.33 s"),
        _f(
            "max_concurrent_skills_process",
            "concurrent Skills (processes)",
            "",
            thesis=150,
            thesis_source="§5.4.1: 150 sequential, 110 at startup",
            goal=1000,
            goal_source="issue 5",
            better="higher",
        ),
        _f(
            "max_concurrent_skills_docker",
            "concurrent Skills (Docker)",
            "",
            thesis=150,
            thesis_source="§5.4.1",
            goal=300,
            goal_source="issue 5",
            better="higher",
        ),
        _f(
            "mb_per_extra_skill",
            "agent memory per extra Skill",
            "MB",
            thesis=66.4,
            thesis_source="§5.4.1: 19.97 MB manager + 46.47 MB router",
            goal=2,
            goal_source="issue 5",
        ),
        _f("docker_over_bare", "Docker runtime / bare docker run", "x", goal=1.2, goal_source="issue 5"),
    ],
    "decisions": [
        _f("inference_ms", "decision (inference)", "ms", goal=0.2, goal_source="issue 6"),
        _f("train_step_ms", "training step", "ms", goal=1.0, goal_source="issue 6"),
        _f("module_kb", "decision module memory", "KB", goal=50, goal_source="issue 6"),
        _f(
            "cpu_share_2000_at_1hz", "CPU share, 2000 components at 1 Hz", "of a core", goal=0.10, goal_source="issue 6"
        ),
        _f(
            "component_init_ms",
            "component init without container",
            "ms",
            thesis=890,
            thesis_source="Fig. 5.8: 0.89 ± 0.16 s with container",
            goal=20,
            goal_source="issue 6",
        ),
    ],
    "router": [
        _f(
            "topic_map_ms",
            "time to map a topic",
            "ms",
            thesis=443,
            thesis_source="Fig. 5.9: 443 ± 20 ms",
            goal=10,
            goal_source="issue 7",
        ),
        _f(
            "max_topics",
            "topics mapped by one router",
            "",
            thesis=5000,
            thesis_source="§5.4.1",
            goal=20000,
            goal_source="issue 7",
            better="higher",
        ),
        _f(
            "routed_over_direct",
            "routed / direct rospy throughput",
            "",
            goal=0.6,
            goal_source="issue 7",
            better="higher",
        ),
        _f(
            "delivery_ratio",
            "delivery ratio",
            "",
            thesis=0.9842,
            thesis_source="§5.3.1: 98.42 %",
            goal=1.0,
            goal_source="issue 7",
            better="higher",
        ),
        _f("added_latency_p50_ms", "added latency p50", "ms", goal=0.5, goal_source="issue 7"),
        _f(
            "router_mb",
            "router memory baseline",
            "MB",
            thesis=46.47,
            thesis_source="§5.4.1: 46.47 ± 1.3 MB",
            goal=5,
            goal_source="issue 7",
        ),
        _f(
            "kb_per_topic",
            "memory per topic",
            "KB",
            thesis=10,
            thesis_source="§5.4.1: 10 KB",
            goal=2,
            goal_source="issue 7",
        ),
    ],
    "cloud_components": [
        _f("swarm_over_bare", "cloud start / bare docker service create", "x", goal=1.2, goal_source="issue 8"),
        _f("migration_s", "migration robot→cloud→robot", "s"),
        _f(
            "cloud_component_wall_s",
            "wall time per cloud component, N started at once",
            "s",
            thesis=0.89,
            thesis_source="§5.4.1: 0.89 ± 0.16 s per component init",
        ),
        _f(
            "cloud_components",
            "cloud components for one robot",
            "",
            thesis=250,
            thesis_source="Fig. 5.8: 250 components",
            better="higher",
        ),
    ],
    "vpn": [
        _f("tunnel_up_s", "tunnel up", "s"),
        _f(
            "vpn_latency_ms",
            "latency over the VPN",
            "ms",
            thesis=0.37,
            thesis_source="issue 11: OpenVPN 2.6 here, 0.37 ms",
        ),
        _f("direct_latency_ms", "latency direct", "ms", thesis=0.10, thesis_source="issue 11: bare veth, 0.10 ms"),
        _f(
            "vpn_throughput_mbps",
            "throughput over the VPN",
            "Mbit/s",
            thesis=220,
            thesis_source="§5.2: the testbed's 220 Mb LAN",
            better="higher",
        ),
    ],
    "offloading_quality": [
        _f("cost_over_oracle", "adaptive cost / hindsight oracle", "x", goal=1.05, goal_source="issue 10"),
        _f("adapt_s", "time to adapt after a change", "s", goal=10, goal_source="issue 10"),
        _f("flaps_per_10min", "flaps per 10 min", "", goal=1, goal_source="issue 10"),
        _f("stable_moves_per_10min", "moves per 10 min in a stable phase", "", goal=1, goal_source="issue 22"),
        _f("migrations", "migrations", ""),
    ],
    "usecases": _usecase_figures(),
    "ws_ingest": [
        _f("points_per_s", "metric points stored", "points/s", goal=10_000, goal_source="issue 3", better="higher"),
        _f("lag_p95_ms", "lag to the dashboard p95", "ms", goal=1000, goal_source="issue 3"),
        _f("dropped_connections", "dropped connections", "", goal=0, goal_source="issue 3"),
    ],
    "connect_storm": [
        _f("connected_s", "1,000 robots connecting at once, all connected", "s", goal=5, goal_source="issue 23"),
        _f("dropped", "robots dropped in the storm", "", goal=0, goal_source="issue 23"),
    ],
    "api_load": [
        _f("read_p99_ms", "API read p99", "ms", goal=50, goal_source="issue 4"),
        _f("list_p99_ms", "robot list p99", "ms", goal=50, goal_source="issue 4"),
        _f("info_p99_ms", "robot info p99", "ms", goal=50, goal_source="issue 4"),
    ],
    "authz": [
        _f("api_p99_over_before", "API read p99 with role checks / without", "x", goal=1.1, goal_source="issue 34"),
        _f("audit_rows_per_s", "audit entries written", "rows/s", better="higher"),
        _f("audit_verify_rows_per_s", "audit chain verified", "rows/s", better="higher"),
        _f("role_matrix_cases", "role matrix cases", "", better="higher"),
        _f("role_matrix_violations", "role matrix violations", "", goal=0, goal_source="issue 34"),
    ],
    "rollouts": [
        _f("rollout_1000_s", "a release rolled out to 1,000 robots", "s", goal=60, goal_source="issue 35"),
        _f(
            "bad_release_robots_touched",
            "robots a bad release reached (canary 100)",
            "",
            goal=100,
            goal_source="issue 35",
        ),
        _f("rollback_s", "rollback of a bad release", "s", goal=15, goal_source="issue 35"),
        _f("offline_converge_s", "an offline robot converging once back", "s", goal=5, goal_source="issue 35"),
        _f("api_p99_ms_during_rollout", "API read p99 during a rollout", "ms", goal=50, goal_source="issue 35"),
    ],
    "logs": [
        _f(
            "lines_per_s_stored",
            "a flooding component's lines stored",
            "lines/s",
            goal=20_000,
            goal_source="issue 36",
            better="higher",
        ),
        _f("tail_p95_ms", "printed on the robot to a live tail p95", "ms", goal=250, goal_source="issue 36"),
        _f(
            "metrics_lag_under_flood_over_quiet",
            "the robot's metrics lag under a 50,000 lines/s flood / quiet",
            "x",
            goal=1.2,
            goal_source="issue 36",
        ),
        _f("query_1m_lines_ms", "a text query over 1M stored lines", "ms", goal=500, goal_source="issue 36"),
        _f("cli_start_ms", "`bridgeos --help` wall time", "ms", goal=300, goal_source="issue 36"),
    ],
    "tenk": [
        _f("connect_10k_s", "10,000 robots connected to one daphne at once", "s", goal=10, goal_source="issue 37"),
        _f("connect_10k_rejected", "handshakes or logins rejected in that storm", "", goal=0, goal_source="issue 37"),
        _f("idle_cpu_pct_10k", "one daphne holding 10,000 idle robots", "% of a core", goal=10, goal_source="issue 37"),
        _f("kb_per_robot", "daphne's resident memory per connected robot", "KiB"),
        _f(
            "ingest_points_per_s_one_process",
            "points/s stored by one process at ack p95 <= 1 s",
            "points/s",
            goal=30_000,
            goal_source="issue 37",
            better="higher",
        ),
        _f("api_p99_ms_10k", "Robot API read p99 among 10,000 robots", "ms", goal=50, goal_source="issue 37"),
        _f("simulator_cpu_pct", "the simulated fleet's own CPU", "% of a core"),
    ],
    "dashboard": [
        _f("first_render_s", "fleet page first render", "s", goal=1.0, goal_source="issue 9"),
        _f("update_lag_s", "metric to row lag p95", "s", goal=1.0, goal_source="issue 9"),
    ],
    "bridges": [
        _f(
            "rosbridge_msgs_per_s",
            "rosbridge 100 B msgs/s to one viewer via the cloud",
            "msgs/s",
            goal=10_000,
            goal_source="issue 19",
            better="higher",
        ),
        _f(
            "foxglove_msgs_per_s",
            "Foxglove 100 B msgs/s to one viewer via the cloud",
            "msgs/s",
            goal=10_000,
            goal_source="issue 19",
            better="higher",
        ),
        _f("cloud_added_latency_p50_ms", "latency the cloud adds over the robot's door p50", "ms"),
        _f(
            "pointcloud_10_viewers_p95_ms",
            "1 MB PointCloud2 at 10 Hz to 10 viewers, lag p95",
            "ms",
            goal=200,
            goal_source="issue 19",
        ),
        _f("pointcloud_link_over_delivered", "robot-link bytes over bytes the 10 viewers got", "ratio"),
        _f("image_json_ms", "640x480 image to rosbridge JSON", "ms", thesis=269, thesis_source="rosbridge_suite #367"),
        _f("image_cbor_ms", "640x480 image to rosbridge CBOR", "ms", thesis=1.5, thesis_source="rosbridge_suite #367"),
        _f("mcap_write_mb_per_s", "MCAP recorder write", "MB/s", better="higher"),
    ],
    "metrics_overhead": [
        _f("ingest_overhead_pct", "ingest CPU per point, metrics on vs off", "%", goal=3, goal_source="issue 21"),
        _f("router_overhead_pct", "router msgs/s lost to /metrics scrapes", "%", goal=3, goal_source="issue 21"),
        _f("scrape_ms", "cloud /metrics scrape, 1,000 robots", "ms", goal=50, goal_source="issue 21"),
    ],
}
