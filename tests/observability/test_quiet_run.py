"""`make run`'s terminal: one status line per part and the login; the parts' output goes to named files."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time

import pytest

from tests.conftest import ROOT, free_port

pytestmark = [pytest.mark.slow, pytest.mark.timeout(180)]


def test_make_run_prints_status_lines_and_keeps_the_parts_output_in_files(tmp_path):
    data = tmp_path / "data"
    port = free_port()
    env = {
        key: value
        for key, value in os.environ.items()
        if key not in ("DATABASE_URL", "PROMETHEUS_MULTIPROC_DIR", "BRIDGEOS_DATA_DIR")
    }
    env.update(
        BRIDGEOS_DATA_DIR=str(data),  # a fresh start: an empty data dir, the embedded SQLite database
        BRIDGEOS_PORT=str(port),
        BRIDGEOS_DEMO_ROBOTS="1",
        BRIDGEOS_DEMO_USECASES="0",
        BRIDGEOS_DEMO_METRICS_PORT=str(free_port()),
        BRIDGEOS_CLOUD_RUNTIME="process",
    )
    process = subprocess.Popen(
        ["bash", "scripts/run.sh"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        start_new_session=True,
    )
    lines = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = process.stdout.readline()
            assert line, "make run ended early:\n" + "".join(lines)
            lines.append(line)
            if "Press Ctrl-C" in line:
                break
        # The demo robot connects and starts its Skill meanwhile: none of it may reach the terminal.
        access_log = data / "logs" / "daphne.log"
        deadline = time.monotonic() + 90
        while "/skill/" not in access_log.read_text() and time.monotonic() < deadline:
            assert process.poll() is None, "make run ended early:\n" + "".join(lines)
            time.sleep(0.5)
    finally:
        os.killpg(process.pid, signal.SIGINT)
        rest, _ = process.communicate(timeout=60)
    output = "".join(lines) + rest
    assert not re.search(r"warn|error|traceback|GET /|POST /", output, re.IGNORECASE), output
    statuses = [line.split(":")[0].strip() for line in lines if line.startswith("  ") and ":" in line]
    for part in ("database", "runtime", "celery", "daphne", "demo", "metrics"):
        assert statuses.count(part) == 1, output
    assert re.search(r"Operator account created: operator / \S+", output), output
    logs = data / "logs"
    for name in ("daphne.log", "celery.log", "demo_fleet.log"):
        assert str(logs / name) in output
        assert (logs / name).stat().st_size > 0, name
    assert "/skill/" in (logs / "daphne.log").read_text()  # the demo fleet started its robot's Skill
