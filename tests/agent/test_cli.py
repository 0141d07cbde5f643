"""Test the bridgeos-agent command line through main()."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from bridgeos_agent import __version__
from bridgeos_agent.cli import main


def test_version_prints_the_version(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["version"]) == 0
    assert capsys.readouterr().out.strip() == __version__


def test_help_exits_zero(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--help"]) == 0
    assert "validate" in capsys.readouterr().out


def test_no_command_prints_help_and_fails(capsys: pytest.CaptureFixture[str]) -> None:
    assert main([]) == 2
    assert "usage" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("kind", "title"), [("skill", "bridgeOS Skill configuration"), ("robot", "bridgeOS Robot configuration")]
)
def test_schema_prints_json_schema(kind: str, title: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["schema", kind]) == 0
    schema = json.loads(capsys.readouterr().out)
    assert schema["title"] == title
    assert schema["$schema"].startswith("https://json-schema.org/")


def test_validate_accepts_the_sample(
    tmp_path: Path, sample: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "skill.json"
    path.write_text(json.dumps(sample))
    assert main(["validate", str(path)]) == 0
    assert "valid skill 'people-detection'" in capsys.readouterr().out


def test_validate_reports_field_errors_and_exits_one(
    tmp_path: Path, sample: dict[str, Any], capsys: pytest.CaptureFixture[str]
) -> None:
    sample["components"]["detector"]["resources"]["cpu"] = -2
    sample["components"]["detector"]["links"] = ["ghost"]
    path = tmp_path / "skill.json"
    path.write_text(json.dumps(sample))
    assert main(["validate", str(path)]) == 1
    err = capsys.readouterr().err
    assert "components.detector.resources.cpu:" in err


def test_validate_reports_malformed_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "skill.json"
    path.write_text("{nope")
    assert main(["validate", str(path)]) == 1
    assert "invalid skill configuration" in capsys.readouterr().err


def test_validate_robot_config(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "robot.json"
    path.write_text(json.dumps({"heuristic": "nope"}))
    assert main(["validate", "--kind", "robot", str(path)]) == 1
    assert "heuristic:" in capsys.readouterr().err


def test_validate_missing_file_fails_clearly(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", str(tmp_path / "absent.json")]) == 2
    assert "cannot read" in capsys.readouterr().err


@pytest.fixture
def clean_env(monkeypatch: pytest.MonkeyPatch) -> pytest.MonkeyPatch:
    """Remove the agent's environment variables."""
    for name in ("BRIDGEOS_MASTER", "BRIDGEOS_ROBOT", "BRIDGEOS_TOKEN", "BRIDGEOS_TOKEN_FILE"):
        monkeypatch.delenv(name, raising=False)
    return monkeypatch


def test_run_without_master_names_the_missing_options(
    clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["run"]) == 2
    err = capsys.readouterr().err
    assert "--master (or BRIDGEOS_MASTER)" in err
    assert "--token (or BRIDGEOS_TOKEN)" in err


def test_run_refuses_a_token_file_it_cannot_read(
    clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    missing = tmp_path / "robot.token"
    assert main(["run", "--master", "ws://127.0.0.1:8000", "--robot", "r1", "--token-file", str(missing)]) == 2
    assert f"--token-file cannot read {missing}" in capsys.readouterr().err


def test_the_token_file_gives_the_token_when_none_is_given(clean_env: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from bridgeos_agent.agent import settings_from_args
    from bridgeos_agent.cli import _check_connection_args, build_parser

    (tmp_path / "robot.token").write_text("brt_from-file\n")
    clean_env.setenv("BRIDGEOS_TOKEN_FILE", str(tmp_path / "robot.token"))
    parser = build_parser()
    args = parser.parse_args(["run", "--master", "ws://127.0.0.1:8000", "--robot", "r1"])
    _check_connection_args(parser, args)
    settings = settings_from_args(args)
    assert (settings.token, settings.token_file) == ("brt_from-file", tmp_path / "robot.token")


@pytest.mark.parametrize("url", ["http://host:8000", "ws://", "ws://host:99999", "host:8000"])
def test_run_rejects_invalid_master_url(
    url: str, clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["run", "--master", url, "--robot", "r1", "--token", "t"]) == 2
    assert "invalid master URL" in capsys.readouterr().err


def test_run_rejects_invalid_master_from_env(clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    clean_env.setenv("BRIDGEOS_MASTER", "ftp://x")
    assert main(["run", "--robot", "r1", "--token", "t"]) == 2
    assert "invalid master URL" in capsys.readouterr().err


def test_run_options_come_from_the_environment(clean_env: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from bridgeos_agent.agent import settings_from_args
    from bridgeos_agent.cli import build_parser

    clean_env.setenv("BRIDGEOS_MASTER", "ws://127.0.0.1:8000")
    clean_env.setenv("BRIDGEOS_ROBOT", "robot-1")
    clean_env.setenv("BRIDGEOS_TOKEN", "secret-token")
    clean_env.setenv("BRIDGEOS_RUNTIME", "docker")
    clean_env.setenv("BRIDGEOS_DATA_DIR", str(tmp_path))
    clean_env.setenv("BRIDGEOS_SIMULATE", "1")
    settings = settings_from_args(build_parser().parse_args(["run", "--sim-cpu", "4"]))
    assert (settings.master, settings.robot, settings.token) == ("ws://127.0.0.1:8000", "robot-1", "secret-token")
    assert settings.runtime == "docker" and settings.simulate and settings.data_dir == tmp_path
    assert settings.simulated is not None and settings.simulated.cpu == 4.0


@pytest.mark.parametrize("value", ["0", "-1", "nan", "inf", "two"])
def test_run_rejects_a_bad_simulated_resource(
    value: str, clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["run", "--master", "ws://h:1", "--robot", "r", "--token", "t", "--sim-cpu", value]) == 2
    assert "--sim-cpu" in capsys.readouterr().err


def test_the_simulated_links_low_point_is_a_setting_at_most_its_peak(
    clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    from bridgeos_agent.agent import settings_from_args
    from bridgeos_agent.cli import build_parser

    def simulated(*options: str):
        return settings_from_args(build_parser().parse_args(["run", "--simulate", *options])).simulated

    assert (simulated().bandwidth, simulated().bandwidth_min) == (100.0, 5.0)  # 5 % of the peak by default
    assert simulated("--sim-bandwidth", "300").bandwidth_min == 15.0
    low = simulated("--sim-bandwidth", "300", "--sim-bandwidth-min", "120")
    assert (low.bandwidth_min, min(low.bandwidth_now(t) for t in range(0, 120))) == (120.0, pytest.approx(120, abs=1))
    run = ["run", "--master", "ws://127.0.0.1:1", "--robot", "r", "--token", "t", "--simulate"]
    assert main([*run, "--sim-bandwidth", "50", "--sim-bandwidth-min", "60"]) == 2
    assert "--sim-bandwidth-min 60 is above the peak --sim-bandwidth 50" in capsys.readouterr().err
    assert main([*run, "--sim-bandwidth-min", "0"]) == 2
    assert "--sim-bandwidth-min" in capsys.readouterr().err


def test_run_rejects_unknown_runtime(clean_env: pytest.MonkeyPatch) -> None:
    assert main(["run", "--master", "ws://h:1", "--robot", "r", "--token", "t", "--runtime", "vm"]) == 2


def test_run_rejects_data_dir_that_is_a_file(
    tmp_path: Path, clean_env: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    file = tmp_path / "file"
    file.write_text("")
    args = ["run", "--master", "ws://h:1", "--robot", "r", "--token", "t", "--data-dir", str(file)]
    assert main(args) == 2
    assert "not a directory" in capsys.readouterr().err
