"""The robot's token file: read at start, replaced whole and private when the cloud re-keys the robot."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from bridgeos_agent.tokenfile import TokenFileError, read_token_file, write_token_file


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_a_written_token_is_read_back_from_a_file_only_its_user_reads(tmp_path: Path) -> None:
    path = tmp_path / "robot.token"
    write_token_file(path, "brt_first")
    assert path.read_text() == "brt_first\n"
    assert mode(path) == 0o600
    assert read_token_file(path) == "brt_first"


def test_a_new_token_replaces_a_readable_file_and_leaves_nothing_beside_it(tmp_path: Path) -> None:
    path = tmp_path / "robot.token"
    path.write_text("brt_old\n")
    path.chmod(0o644)
    write_token_file(path, "brt_new")
    assert read_token_file(path) == "brt_new"
    assert mode(path) == 0o600
    assert [child.name for child in tmp_path.iterdir()] == ["robot.token"]


def test_a_failed_write_leaves_the_old_token_whole(tmp_path: Path) -> None:
    path = tmp_path / "robot.token"
    write_token_file(path, "brt_old")
    # Where the new file would be written is taken (a directory, refused even to root).
    (tmp_path / f".robot.token.{os.getpid()}.tmp").mkdir()
    with pytest.raises(IsADirectoryError):
        write_token_file(path, "brt_new")
    assert read_token_file(path) == "brt_old"


@pytest.mark.parametrize(
    ("content", "said"),
    [(None, "cannot read"), ("", "is empty"), ("  \n", "is empty"), ("two words\n", "does not hold a token")],
)
def test_a_file_without_a_token_is_refused_without_echoing_it(tmp_path: Path, content: str | None, said: str) -> None:
    path = tmp_path / "robot.token"
    if content is not None:
        path.write_text(content)
    with pytest.raises(TokenFileError) as caught:
        read_token_file(path)
    assert said in str(caught.value)
    assert "words" not in str(caught.value)
