"""The stack's cloud image copies every app of the project: one left out fails its build (manage.py)."""

from __future__ import annotations

import re

from django.conf import settings

from tests.conftest import ROOT


def test_the_cloud_image_copies_every_local_app() -> None:
    script = (ROOT / "docker" / "build-images.sh").read_text()
    trees = set(re.search(r"^CLOUD_TREES=\(([^)]*)\)", script, re.MULTILINE).group(1).split())  # type: ignore[union-attr]
    local = {app.split(".")[0] for app in settings.INSTALLED_APPS if (ROOT / app.split(".")[0]).is_dir()}
    assert local <= trees, f"apps the cloud image would not copy: {sorted(local - trees)}"
