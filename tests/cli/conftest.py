"""The `bridgeos` console script in a virtual environment of its own, run as a subprocess.

The environment is built offline, without the network: a wheel of `cli/` is built with the
project's setuptools, installed with `pip --python NEW --no-deps --no-index`, and its
dependencies (click, httpx, websockets and what they need, resolved from their metadata with
markers evaluated) are copied file by file, dist-info included, from the project's own venv.
So the CLI runs with exactly its declared dependencies and nothing else: no Django, no agent.
"""

from __future__ import annotations

import queue
import shutil
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from importlib import metadata
from pathlib import Path

import pytest

from tests.conftest import ROOT

CLI_REQUIRES = ("click", "httpx", "websockets")


def requirement_closure(names: tuple[str, ...]) -> list[metadata.Distribution]:
    """Return the installed distributions these names need, transitively, for this interpreter (no extras)."""
    try:
        from packaging.requirements import Requirement
    except ImportError:  # not every venv has packaging itself; pip always carries a copy
        from pip._vendor.packaging.requirements import Requirement

    found: dict[str, metadata.Distribution] = {}
    pending = list(names)
    while pending:
        name = pending.pop()
        dist = metadata.distribution(name)
        key = dist.metadata["Name"].lower().replace("_", "-")
        if key in found:
            continue
        found[key] = dist
        for text in dist.requires or []:
            requirement = Requirement(text)
            if requirement.marker is None or requirement.marker.evaluate({"extra": ""}):
                pending.append(requirement.name)
    return list(found.values())


def copy_distribution(dist: metadata.Distribution, site: Path) -> None:
    """Copy an installed distribution's files (its dist-info too) into another site-packages."""
    for file in dist.files or []:
        relative = Path(str(file))
        # Console scripts live outside site-packages; byte code is rebuilt by the new interpreter.
        if relative.parts[0] == ".." or "__pycache__" in relative.parts:
            continue
        source = Path(str(dist.locate_file(file)))
        if source.is_file():
            target = site / relative
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, target)


def build_cli_venv(where: Path) -> Path:
    """Build the CLI's own venv under ``where`` and return its `bridgeos` script."""
    source = where / "source"
    # Built from a copy: setuptools writes build/ and egg-info beside the sources it builds.
    shutil.copytree(ROOT / "cli", source, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    wheels = where / "wheels"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run([*pip, "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", wheels, source], check=True)
    venv = where / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", venv], check=True)
    python = venv / "bin" / "python"
    (wheel,) = wheels.glob("bridgeos_cli-*.whl")
    subprocess.run([*pip, "--python", python, "install", "--no-deps", "--no-index", wheel], check=True)
    site = Path(
        subprocess.run(
            [python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
            check=True,
            capture_output=True,
            text=True,
        ).stdout.strip()
    )
    for dist in requirement_closure(CLI_REQUIRES):
        copy_distribution(dist, site)
    # Every declared requirement is met by what was copied, and nothing more is there.
    subprocess.run([*pip, "--python", python, "check"], check=True)
    return venv / "bin" / "bridgeos"


@pytest.fixture(scope="session")
def bridgeos(tmp_path_factory) -> Path:
    """Return the `bridgeos` script of a venv holding only the CLI and its dependencies."""
    return build_cli_venv(tmp_path_factory.mktemp("cli-venv"))


@dataclass
class Cli:
    """Runs `bridgeos` as a user would: a clean environment, its own home and config directory."""

    script: Path
    home: Path
    env: dict[str, str]

    def __call__(self, *args: str, input: str | None = None, timeout: float = 60, **env: str) -> Result:
        started = time.monotonic()
        done = subprocess.run(
            [str(self.script), *args],
            env={**self.env, **env},
            input=input,
            capture_output=True,
            text=True,
            timeout=timeout,
        )
        return Result(done.returncode, done.stdout, done.stderr, time.monotonic() - started)

    def popen(self, *args: str, **env: str) -> subprocess.Popen:
        """Start a long-running command (`-f`), its stdout line-buffered text."""
        return subprocess.Popen(
            [str(self.script), *args],
            env={**self.env, **env},
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            bufsize=1,
        )

    @property
    def config_file(self) -> Path:
        return self.home / ".config" / "bridgeos" / "config.json"


@dataclass
class Result:
    code: int
    out: str
    err: str
    seconds: float

    def json(self):
        import json

        return json.loads(self.out)

    def __str__(self) -> str:
        return f"exit {self.code}\n--- stdout\n{self.out}\n--- stderr\n{self.err}"


@pytest.fixture
def cli(bridgeos: Path, tmp_path: Path) -> Cli:
    """Return a runner of `bridgeos` for one user: its own HOME, no PYTHONPATH, nothing of the project's env."""
    home = tmp_path / "home"
    home.mkdir()
    env = {
        "PATH": f"{bridgeos.parent}:/usr/bin:/bin",
        "HOME": str(home),
        "LANG": "C.UTF-8",
        # No XDG_CONFIG_HOME: the CLI falls back to ~/.config, as on most laptops.
        "TERM": "dumb",
    }
    return Cli(bridgeos, home, env)


def lines_of(process: subprocess.Popen) -> queue.Queue[str]:
    """Wait until a `-f` command says it follows (on stderr); return a queue of the lines it prints on stdout."""
    received: queue.Queue[str] = queue.Queue()
    said = process.stderr.readline()
    assert said.startswith("Following"), f"{said}{process.stderr.read() if process.poll() is not None else ''}"

    def read() -> None:
        for line in process.stdout:
            received.put(line)

    threading.Thread(target=read, daemon=True).start()
    return received


def next_line(received: queue.Queue[str], process: subprocess.Popen, match: Callable[[str], bool], timeout=15) -> str:
    """Return the first line printed that matches, or fail with what the process said."""
    try:
        while True:
            line = received.get(timeout=timeout)
            if match(line):
                return line
    except queue.Empty:
        process.terminate()
        raise AssertionError(f"no matching line within {timeout} s; stderr: {process.communicate()[1]}") from None


def stop(process: subprocess.Popen) -> None:
    process.terminate()
    process.wait(timeout=10)
