"""Helpers to scrape Prometheus endpoints and read samples, and to run Debian's prometheus and promtool."""

from __future__ import annotations

import json
import shutil
import subprocess
import time
import urllib.parse
import urllib.request
from collections.abc import Mapping
from pathlib import Path

from prometheus_client.parser import text_string_to_metric_families

ROOT = Path(__file__).resolve().parents[2]
RULES = ROOT / "docker" / "prometheus" / "alerts.yml"
RULE_TESTS = ROOT / "docker" / "prometheus" / "alerts_test.yml"
DASHBOARD = ROOT / "docker" / "grafana" / "bridgeos.json"
PROMETHEUS = shutil.which("prometheus") or "/usr/bin/prometheus"
PROMTOOL = shutil.which("promtool") or "/usr/bin/promtool"


def fetch(url: str, headers: Mapping[str, str] | None = None) -> str:
    """GET a URL and return its body as text."""
    request = urllib.request.Request(url, headers=dict(headers or {}))
    with urllib.request.urlopen(request, timeout=10) as response:
        return response.read().decode()


def samples(text: str) -> dict[tuple[str, frozenset[tuple[str, str]]], float]:
    """Return every sample of an exposition keyed by (sample name, labels)."""
    found: dict[tuple[str, frozenset[tuple[str, str]]], float] = {}
    for family in text_string_to_metric_families(text):
        for sample in family.samples:
            found[(sample.name, frozenset(sample.labels.items()))] = sample.value
    return found


def value(text: str, name: str, **labels: str) -> float:
    """Return the sum of the samples called name whose labels include the given ones (0 if none)."""
    wanted = set(labels.items())
    return sum(v for (sample, have), v in samples(text).items() if sample == name and wanted <= have)


def promtool_check_metrics(text: str) -> subprocess.CompletedProcess[str]:
    """Run `promtool check metrics` on an exposition."""
    return subprocess.run([PROMTOOL, "check", "metrics"], input=text, capture_output=True, text=True, timeout=30)


class Prometheus:
    """A real prometheus server with a temporary config, queried over its HTTP API."""

    def __init__(self, workdir: Path, port: int, targets: Mapping[str, tuple[str, str]], *, token: str = "") -> None:
        self.url = f"http://127.0.0.1:{port}"
        scrape = []
        for job, (address, path) in targets.items():
            entry = (
                f"  - job_name: {job}\n    metrics_path: {path}\n    scrape_interval: 1s\n"
                f"    static_configs:\n      - targets: ['{address}']\n"
            )
            if token and job == "bridgeos-cloud":
                entry += f"    authorization:\n      credentials: {token}\n"
            scrape.append(entry)
        workdir.mkdir(parents=True, exist_ok=True)
        config = workdir / "prometheus.yml"
        config.write_text(
            "global:\n  scrape_interval: 1s\n  evaluation_interval: 1s\n"
            f"rule_files:\n  - {RULES}\n"
            "scrape_configs:\n" + "".join(scrape)
        )
        self.log = workdir / "prometheus.log"
        with self.log.open("wb") as out:
            self.process = subprocess.Popen(
                [
                    PROMETHEUS,
                    f"--config.file={config}",
                    f"--storage.tsdb.path={workdir / 'data'}",
                    f"--web.listen-address=127.0.0.1:{port}",
                ],
                stdout=out,
                stderr=subprocess.STDOUT,
            )

    def api(self, path: str, **params: str) -> dict:
        """Call the HTTP API and return its data, raising on an error status."""
        query = urllib.parse.urlencode(params)
        answer = json.loads(fetch(f"{self.url}/api/v1/{path}?{query}"))
        if answer.get("status") != "success":
            raise AssertionError(f"prometheus {path} {params}: {answer}")
        return answer["data"]

    def wait_ready(self, timeout: float = 30) -> None:
        """Wait until the server answers its readiness check."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"prometheus exited: {self.log.read_text()[-2000:]}")
            try:
                fetch(f"{self.url}/-/ready")
                return
            except OSError:
                time.sleep(0.2)
        raise TimeoutError("prometheus did not get ready")

    def query(self, expr: str) -> list[dict]:
        """Run an instant query and return its result vector."""
        return self.api("query", query=expr)["result"]

    def wait_for(self, expr: str, timeout: float = 30) -> list[dict]:
        """Poll an instant query until it returns something."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            result = self.query(expr)
            if result:
                return result
            time.sleep(0.5)
        raise AssertionError(f"{expr} returned nothing within {timeout} s; targets: {self.api('targets')}")

    def stop(self) -> None:
        """Stop the server."""
        self.process.terminate()
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
