"""The `bridgeos` package on its own: installs without Django or the agent, starts fast, fails with clear exit codes."""

from __future__ import annotations

import statistics
import subprocess

import pytest

from tests.conftest import free_port

pytestmark = pytest.mark.slow


def test_the_cli_venv_holds_neither_django_nor_the_agent(cli):
    version = cli("--version")
    assert version.code == 0 and "bridgeos, version 0.1.0" in version.out, version
    python = cli.script.parent / "python"
    for module in ("django", "bridgeos_agent", "bridgeos_cloud", "pydantic"):
        done = subprocess.run([python, "-c", f"import {module}"], env=cli.env, capture_output=True, text=True)
        assert done.returncode != 0, f"{module} is importable in the CLI's own venv"


def test_help_lists_every_command_with_examples_and_exit_codes_fast(cli):
    runs = [cli("--help") for _ in range(5)]
    assert all(run.code == 0 for run in runs), runs[0]
    for command in ("login", "robots", "skills", "components", "logs", "events", "recordings", "metrics", "images"):
        assert f"  {command} " in runs[0].out
    assert "Examples:" in runs[0].out and "Exit codes:" in runs[0].out
    # The benchmark's cli_start_ms is the wall time of `bridgeos --help`; its goal is 300 ms.
    assert statistics.median(run.seconds for run in runs) < 0.3, [run.seconds for run in runs]
    timed = subprocess.run(
        [cli.script.parent / "python", "-c", "from bridgeos_cli.timing import cli_start_ms; print(cli_start_ms())"],
        env=cli.env,
        capture_output=True,
        text=True,
        check=True,
    )
    assert 0 < float(timed.stdout) < 300, timed


@pytest.mark.parametrize(
    "command",
    [
        ["login"],
        ["robots", "ls"],
        ["robots", "show"],
        ["skills", "add"],
        ["skills", "start"],
        ["components", "migrate"],
        ["logs"],
        ["events"],
        ["recordings", "download"],
        ["metrics", "query"],
        ["images", "ls"],
        ["rollouts", "create"],
        ["rollouts", "abort"],
    ],
)
def test_every_command_has_help_with_an_example(cli, command):
    shown = cli(*command, "--help")
    assert shown.code == 0, shown
    assert "bridgeos " + " ".join(command) in shown.out and "Example" in shown.out, shown


def test_shell_completion_completes_commands_and_prints_scripts(cli):
    script = cli("completion", "bash")
    assert script.code == 0 and "_BRIDGEOS_COMPLETE" in script.out
    for shell in ("zsh", "fish"):
        assert cli("completion", shell).code == 0
    completed = cli(_BRIDGEOS_COMPLETE="bash_complete", COMP_WORDS="bridgeos rob", COMP_CWORD="1")
    assert completed.code == 0 and "robots" in completed.out, completed
    nested = cli(_BRIDGEOS_COMPLETE="bash_complete", COMP_WORDS="bridgeos rollouts pa", COMP_CWORD="2")
    assert "pause" in nested.out, nested


def test_not_logged_in_bad_usage_and_an_unreachable_cloud_exit_with_their_own_codes(cli):
    missing = cli("robots", "ls")
    assert missing.code == 3 and "bridgeos login" in missing.err, missing
    usage = cli("logs", "a/b/c/d")
    assert usage.code == 2 and "ROBOT[/SKILL[/COMPONENT]]" in usage.err, usage
    bad_time = cli("logs", "r1", "--since", "yesterday-ish", BRIDGEOS_URL="http://127.0.0.1:1", BRIDGEOS_TOKEN="t")
    assert bad_time.code == 2 and "--since" in bad_time.err, bad_time
    port = free_port()  # nobody listens there
    down = cli("robots", "ls", BRIDGEOS_URL=f"http://127.0.0.1:{port}", BRIDGEOS_TOKEN="t")
    assert down.code == 5 and f"127.0.0.1:{port}" in down.err, down
    follow = cli("events", "-f", BRIDGEOS_URL=f"http://127.0.0.1:{port}", BRIDGEOS_TOKEN="t")
    assert follow.code == 5, follow
