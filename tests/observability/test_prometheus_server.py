"""A real Prometheus (Debian's) scrapes a live daphne and a live agent; the series come back over its API."""

from __future__ import annotations

import json
import re
import subprocess
import time

import pytest
from django.contrib.auth import get_user_model

from robots.models import Robot
from robots.services import create_robot
from tests.conftest import BIN, free_port
from tests.logguard import watch

from .promutil import DASHBOARD, PROMETHEUS, PROMTOOL, RULE_TESTS, RULES, Prometheus, fetch, promtool_check_metrics

pytestmark = [pytest.mark.django_db(transaction=True), pytest.mark.timeout(180)]

# Words in a PromQL expression that are not metric names.
PROMQL_WORDS = {
    "sum", "rate", "increase", "histogram_quantile", "by", "on", "and", "or", "count", "deriv", "le", "time",
}  # fmt: skip


def test_alert_rules_pass_promtool_check_and_their_unit_tests():
    checked = subprocess.run([PROMTOOL, "check", "rules", str(RULES)], capture_output=True, text=True, timeout=60)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    tested = subprocess.run(
        [PROMTOOL, "test", "rules", str(RULE_TESTS)], capture_output=True, text=True, timeout=60, cwd=RULES.parent
    )
    assert tested.returncode == 0, tested.stdout + tested.stderr
    assert "SUCCESS" in tested.stdout


def dashboard_queries() -> list[str]:
    panels = json.loads(DASHBOARD.read_text())["panels"]
    return [target["expr"] for panel in panels for target in panel["targets"]]


def metric_names(expr: str) -> set[str]:
    """Return the metric names an expression reads (identifiers outside label matchers and strings)."""
    bare = re.sub(r"\{[^}]*\}|\"[^\"]*\"|\[[^\]]*\]", "", expr)
    bare = re.sub(r"\b(by|on)\s*\([^)]*\)", "", bare)
    return {word for word in re.findall(r"[a-zA-Z_:][a-zA-Z0-9_:]*", bare) if word not in PROMQL_WORDS}


def test_prometheus_scrapes_the_cloud_and_an_agent_and_every_dashboard_query_runs(
    daphne_server, celery_worker_process, tmp_path
):
    from monitoring.tasks import prune_metrics

    owner = get_user_model().objects.create_user("prom-owner")
    _, token = create_robot("prom-agent", owner)
    agent_port, prometheus_port = free_port(), free_port()
    agent_log = watch(tmp_path / "agent.log").open("wb")
    agent = subprocess.Popen(
        [
            str(BIN / "bridgeos-agent"), "run", "--master", daphne_server.ws_url, "--robot", "prom-agent",
            "--token", token, "--simulate", "--runtime", "process", "--data-dir", str(tmp_path / "agent"),
            "--metrics", f"127.0.0.1:{agent_port}",
        ],
        stdout=agent_log,
        stderr=subprocess.STDOUT,
    )  # fmt: skip
    prometheus = None
    try:
        # A real task in the real worker, so the Celery families have a series.
        assert prune_metrics.delay(older_than_seconds=10 * 365 * 86400).get(timeout=60) == 0
        deadline = time.monotonic() + 30
        while not Robot.objects.get(id="prom-agent").connected:
            assert agent.poll() is None and time.monotonic() < deadline, (tmp_path / "agent.log").read_text()
            time.sleep(0.2)

        cloud_text = fetch(daphne_server.url + "/metrics")
        agent_text = fetch(f"http://127.0.0.1:{agent_port}/metrics")
        for text in (cloud_text, agent_text):
            checked = promtool_check_metrics(text)
            assert checked.returncode == 0, checked.stdout + checked.stderr

        prometheus = Prometheus(
            tmp_path / "prometheus",
            prometheus_port,
            {
                "bridgeos-cloud": (f"127.0.0.1:{daphne_server.port}", "/metrics"),
                "bridgeos-agent": (f"127.0.0.1:{agent_port}", "/metrics"),
            },
        )
        prometheus.wait_ready()
        prometheus.wait_for('count(up{job=~"bridgeos-.*"} == 1) == 2')
        prometheus.wait_for('bridgeos_robot_connected{robot="prom-agent"} == 1')
        prometheus.wait_for('bridgeos_agent_link_up{robot="prom-agent"} == 1')
        prometheus.wait_for('bridgeos_agent_outbox_frames{robot="prom-agent"}')
        prometheus.wait_for('bridgeos_celery_tasks_total{task="monitoring.tasks.prune_metrics",outcome="success"} >= 1')
        prometheus.wait_for('bridgeos_celery_task_seconds_count{task="monitoring.tasks.prune_metrics"} >= 1')
        # The agent's points arrive at the cloud: received and written, counted across processes.
        prometheus.wait_for("bridgeos_metric_points_received_total > 0")
        prometheus.wait_for("bridgeos_ingest_rows_written_total > 0")

        # Every query of the Grafana dashboard runs, and reads only metrics Prometheus has seen.
        # Known: the names with series, and the families the targets declared (some have no series yet).
        known = set(prometheus.api("label/__name__/values"))
        known |= {item["metric"] for item in prometheus.api("targets/metadata", match_target='{job=~"bridgeos-.*"}')}
        queries = dashboard_queries()
        assert len(queries) >= 20
        for expr in queries:
            assert metric_names(expr), expr
            prometheus.query(expr)  # raises on a query Prometheus refuses
            for name in metric_names(expr):
                family = re.sub(r"_(bucket|count|sum|total)$", "", name)
                assert name in known or family in known, f"{name} in {expr!r} is unknown to Prometheus"

        # The shipped alert rules load into the real server.
        groups = prometheus.api("rules")["groups"]
        rules = [rule for group in groups for rule in group["rules"]]
        assert len(rules) == 7
        assert all(rule["health"] != "err" for rule in rules), rules
    finally:
        agent.terminate()
        agent.wait(timeout=20)
        agent_log.close()
        if prometheus is not None:
            prometheus.stop()


def test_prometheus_and_promtool_come_from_debian():
    assert PROMETHEUS.startswith("/usr/bin/") and PROMTOOL.startswith("/usr/bin/")
