"""The documentation site builds with --strict, and --strict does fail on a broken link."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

from .conftest import ROOT

MKDOCS = Path(sys.executable).parent / "mkdocs"


def build(config: Path, site: Path) -> subprocess.CompletedProcess[str]:
    command = [str(MKDOCS), "build", "--strict", "--config-file", str(config), "--site-dir", str(site)]
    env = {**os.environ, "NO_MKDOCS_2_WARNING": "1"}
    return subprocess.run(command, capture_output=True, text=True, timeout=180, env=env, check=False)


def test_the_site_builds_strictly_with_every_section(tmp_path):
    result = build(ROOT / "mkdocs.yml", tmp_path / "site")
    assert result.returncode == 0, result.stderr
    for page in [
        "index",
        "operators/index",
        "robots/index",
        "skills/tutorial",
        "apps/index",
        "architecture/index",
        "performance/index",
        "reference/protocol",
        "reference/openapi",
        "reference/settings",
    ]:
        assert (tmp_path / "site" / page / "index.html").exists() or (tmp_path / "site" / f"{page}.html").exists(), page
    assert (tmp_path / "site" / "reference" / "openapi.json").exists()


def test_a_broken_link_fails_the_strict_build(tmp_path):
    shutil.copytree(ROOT / "docs", tmp_path / "docs")
    shutil.copy(ROOT / "mkdocs.yml", tmp_path / "mkdocs.yml")
    page = tmp_path / "docs" / "operators" / "fleets.md"
    page.write_text(
        page.read_text() + "\nSee [the missing heading](dashboard.md#no-such-heading) and [a lost page](lost.md).\n"
    )
    result = build(tmp_path / "mkdocs.yml", tmp_path / "site")
    assert result.returncode != 0
    assert "no-such-heading" in result.stderr and "lost.md" in result.stderr
