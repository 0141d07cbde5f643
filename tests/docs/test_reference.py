"""The reference pages are generated from the code, and a page that no longer matches it is caught."""

from __future__ import annotations

import difflib
import json
import re
import subprocess
import sys

from bridgeos_agent.protocol import PAYLOADS, Event
from bridgeos_agent.skillconfig import parse_skill_config

from .conftest import GENERATOR, ROOT

REFERENCE = ROOT / "docs" / "reference"
HAND_WRITTEN = [path for path in (ROOT / "docs").rglob("*.md") if "reference" not in path.relative_to(ROOT).parts]


def test_every_reference_page_is_what_the_code_generates(rendered):
    stale = {}
    for name, text in rendered.items():
        committed = (REFERENCE / name).read_text() if (REFERENCE / name).exists() else ""
        if committed != text:
            diff = difflib.unified_diff(
                committed.splitlines(), text.splitlines(), f"committed/{name}", "code", lineterm=""
            )
            stale[name] = "\n".join(list(diff)[:20])
    assert not stale, "stale reference pages, run `python scripts/docs_reference.py`:\n" + "\n\n".join(stale.values())


def test_the_generator_finds_a_page_that_differs_from_the_code(generator, tmp_path):
    generator.write(tmp_path)
    assert generator.stale(tmp_path) == []
    protocol = tmp_path / "protocol.md"
    protocol.write_text(protocol.read_text().replace("`skill_connect`", "`skill_connnect`"))
    (tmp_path / "settings.md").unlink()
    assert generator.stale(tmp_path) == ["protocol.md", "settings.md"]
    assert generator.main(["--check", "--out", str(tmp_path)]) == 1


def test_check_mode_exits_non_zero_naming_the_stale_page(generator, tmp_path):
    generator.write(tmp_path)
    schema = tmp_path / "skill-config.schema.json"
    schema.write_text(schema.read_text().replace('"skill_id"', '"skill_key"'))
    check = [sys.executable, str(GENERATOR), "--check", "--out", str(tmp_path)]
    stale = subprocess.run(check, capture_output=True, text=True, timeout=120, check=False)
    assert stale.returncode == 1
    assert "skill-config.schema.json is stale" in stale.stderr
    assert "protocol.md" not in stale.stderr
    generator.write(tmp_path)
    assert subprocess.run(check, capture_output=True, text=True, timeout=120, check=False).returncode == 0


def test_the_protocol_page_has_a_section_for_every_event(rendered):
    page = rendered["protocol.md"]
    for event in Event:
        assert f"{{ #{event.value.replace('_', '-')} }}" in page, event
        assert f"`{PAYLOADS[event].__name__}`" in page, event


def test_the_schema_file_is_the_skill_config_json_schema(rendered):
    from bridgeos_agent.skillconfig import skill_config_json_schema

    assert json.loads(rendered["skill-config.schema.json"]) == skill_config_json_schema()


def test_every_setting_the_cloud_reads_is_explained_for_operators(generator):
    explained = (ROOT / "docs" / "operators" / "configuration.md").read_text()
    missing = sorted(name for name in generator.cloud_variables() if f"`{name}`" not in explained)
    assert not missing, f"add these to docs/operators/configuration.md: {missing}"


def test_every_skill_config_shown_in_the_guides_validates():
    shown = 0
    for page in HAND_WRITTEN:
        for block in re.findall(r"```json\n(.*?)```", page.read_text(), re.S):
            if '"skill_id"' in block and '"components"' in block:
                parse_skill_config(block)
                shown += 1
    assert shown >= 2  # the tutorial's and the config guide's at least


def test_every_option_of_the_agent_is_explained_for_robot_owners(generator):
    from bridgeos_agent.cli import build_parser

    explained = (ROOT / "docs" / "robots" / "agent.md").read_text()
    run = generator._subcommands(build_parser())["run"]
    options = [option for action in run._actions for option in action.option_strings if option.startswith("--")]
    missing = [option for option in options if f"`{option}`" not in explained and option != "--help"]
    assert not missing, f"add these to docs/robots/agent.md: {missing}"


def test_every_python_example_in_the_guides_compiles():
    compiled = 0
    for page in HAND_WRITTEN:
        for block in re.findall(r"```python\n(.*?)```", page.read_text(), re.S):
            compile(block, str(page), "exec")
            compiled += 1
    assert compiled >= 5
