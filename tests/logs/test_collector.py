"""Cloud copies' output: what a process copy prints is collected and stored with location "cloud", numbered on."""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest

from logs.collector import collect_all, parse_docker_line, process_log_path
from logs.models import ComponentLog
from skills.models import CloudInstance, Component
from tests.cloud.apiutil import robot_of, user_with_token

pytestmark = pytest.mark.django_db(transaction=True)

SKILL = "people-detection"


def run_copy(path, *lines: str) -> None:
    """Run a real process whose stdout and stderr go to the copy's log file, as the process runtime launches it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    script = "import sys\nfor text in sys.argv[1:]:\n    print(text, file=sys.stderr if 'ERROR' in text else sys.stdout, flush=True)"
    with path.open("ab") as out:
        subprocess.run([sys.executable, "-c", script, *lines], stdout=out, stderr=out, check=True)


def cloud_lines(robot_id: str) -> list[tuple[int, str, str | None]]:
    rows = ComponentLog.objects.filter(robot_id=robot_id, component="detector", location="cloud").order_by("seq")
    return [(row.seq, row.text, row.level_name) for row in rows]


def test_a_process_copys_output_is_stored_once_numbered_on_across_rounds_and_rotation(settings):
    owner, _ = user_with_token("lc-owner")
    robot_of(owner, "lc-bot")
    component = Component.objects.get(skill__robot_id="lc-bot", component_id="detector")
    CloudInstance.objects.create(component=component, desired=CloudInstance.Desired.RUNNING)
    settings.BRIDGEOS = {**settings.BRIDGEOS, "CLOUD_RUNTIME": "process"}
    path = process_log_path("lc-bot", SKILL, "detector")

    run_copy(path, "[INFO] detector up", "ERROR: no camera")
    assert collect_all() == 2
    assert collect_all() == 0  # nothing new: nothing stored twice
    run_copy(path, "frame 1")
    collect_all()
    # The runtime's rotation: the file copied to .log.1 and truncated in place, with a line not collected yet.
    run_copy(path, "just before rotation")
    shutil.copyfile(path, path.with_name(path.name + ".1"))
    path.write_bytes(b"")
    run_copy(path, "after rotation")
    collect_all()
    assert cloud_lines("lc-bot") == [
        (1, "[INFO] detector up", "info"),
        (2, "ERROR: no camera", "error"),
        (3, "frame 1", None),
        (4, "just before rotation", None),
        (5, "after rotation", None),
    ]


def test_dockers_timestamped_lines_are_parsed_to_the_nanosecond():
    assert parse_docker_line("2026-12-04T19:00:00.123456789Z hello world") == (1796410800123456789, "hello world")
    assert parse_docker_line("2026-12-04T19:00:01Z x") == (1796410801000000000, "x")
    assert parse_docker_line("not a timestamp") is None
