"""Test that the agent installs with pip into a fresh venv, without Django."""

from __future__ import annotations

import subprocess
import sys
import venv
from pathlib import Path

import pytest

import bridgeos_agent

AGENT_DIR = Path(__file__).resolve().parents[2] / "agent"


@pytest.mark.slow
def test_pip_install_gives_a_working_cli_without_django(tmp_path: Path) -> None:
    env_dir = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(env_dir)
    python = env_dir / "bin" / "python"
    subprocess.run(
        [str(python), "-m", "pip", "install", "--quiet", "--disable-pip-version-check", str(AGENT_DIR)],
        check=True,
        timeout=600,
    )
    no_django = subprocess.run([str(python), "-c", "import django"], capture_output=True, text=True, timeout=60)
    assert no_django.returncode != 0, "django must not be installed with the agent"
    assert "No module named 'django'" in no_django.stderr

    cli = env_dir / "bin" / "bridgeos-agent"
    help_run = subprocess.run([str(cli), "--help"], capture_output=True, text=True, timeout=60)
    assert help_run.returncode == 0, help_run.stderr
    assert "bridgeOS robot agent" in help_run.stdout
    version_run = subprocess.run([str(cli), "version"], capture_output=True, text=True, timeout=60)
    assert version_run.returncode == 0, version_run.stderr
    assert version_run.stdout.strip() == bridgeos_agent.__version__

    sample = subprocess.run(
        [
            str(python),
            "-c",
            "from bridgeos_agent.skillconfig import load_sample_skill_config as l; print(l().skill_id)",
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert sample.stdout.strip() == "people-detection", sample.stderr
    assert sys.version_info >= (3, 11)
