"""Share fixtures for the agent package's tests."""

from __future__ import annotations

import copy
import json
import subprocess
from importlib import resources
from pathlib import Path
from typing import Any

import pytest

from tests.conftest import BIN, ROOT, free_port, service_env, wait_for_port
from tests.logguard import watch

_SAMPLE = json.loads(
    resources.files("bridgeos_agent").joinpath("samples").joinpath("people_detection.json").read_text()
)


@pytest.fixture
def sample() -> dict[str, Any]:
    """Return a fresh, mutable copy of the people-detection sample Skill config."""
    return copy.deepcopy(_SAMPLE)


class Cloud:
    """A daphne of the test's own on a fixed port, so the test can kill and restart the cloud."""

    def __init__(self, log: Path) -> None:
        self.port = free_port()
        self.log = watch(log)
        self.process: subprocess.Popen | None = None
        self.env: dict[str, str] = {}

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.port}"

    @property
    def ws_url(self) -> str:
        return f"ws://127.0.0.1:{self.port}"

    def start(self) -> None:
        from django.conf import settings as django_settings

        env = service_env(django_settings.DATABASES["default"]["NAME"])
        with self.log.open("ab") as out:
            self.process = subprocess.Popen(
                [str(ROOT / "scripts" / "daphne"), "-b", "127.0.0.1", "-p", str(self.port)],
                cwd=ROOT,
                env={**env, "VIRTUAL_ENV": str(BIN.parent), **self.env},
                stdout=out,
                stderr=subprocess.STDOUT,
            )
        wait_for_port(self.port, self.process)

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.kill()  # a crash, not a polite shutdown
            self.process.wait(10)


@pytest.fixture
def cloud(tmp_path, celery_worker_process) -> Cloud:
    # With a Celery worker: cloud-side launches really run (the process runtime, by default).
    server = Cloud(tmp_path / "daphne.log")
    server.start()
    yield server
    server.stop()
