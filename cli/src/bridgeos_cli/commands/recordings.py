"""`bridgeos recordings`: a robot's MCAP recordings, listed and downloaded with a progress bar."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from ..output import emit_json, fields, json_option, show, state, table
from . import url_path

COLUMNS = [("id", "id"), "status", "topics", "started_at", "duration_s", "message_count", "size_bytes"]
CHUNK = 1 << 16

if TYPE_CHECKING:
    from click._termui_impl import ProgressBar


@click.group()
def recordings() -> None:
    """List and download a robot's MCAP recordings."""


@recordings.command("ls")
@click.argument("robot")
@click.option("-n", "--limit", type=click.IntRange(1, 1000), help="Only the newest N.")
@json_option
def recordings_ls(robot: str, limit: int | None) -> None:
    """List the recordings of ROBOT, newest first.

    \b
    Examples:
      bridgeos recordings ls r1
      bridgeos recordings ls r1 --json | jq -r '.[] | select(.status == "finished") | .id'
    """
    found = state().api().get(f"/api/robot/{url_path(robot)}/recordings", limit=limit)
    show(found, lambda rows: table(rows, COLUMNS, empty="No recordings."))


@recordings.command("show")
@click.argument("robot")
@click.argument("recording")
@json_option
def recordings_show(robot: str, recording: str) -> None:
    """Show one recording.

    \b
    Example:
      bridgeos recordings show r1 6f1c2a...
    """
    found = state().api().get(f"/api/robot/{url_path(robot, 'recordings', recording)}")
    show(found, fields)


@recordings.command("download")
@click.argument("robot")
@click.argument("recording")
@click.option(
    "-o", "--output", type=click.Path(dir_okay=False, writable=True), help="File to write (default: its name)."
)
@click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
@json_option
def recordings_download(robot: str, recording: str, output: str | None, quiet: bool) -> None:
    """Download a finished recording's .mcap file, with a progress bar on stderr.

    \b
    Examples:
      bridgeos recordings download r1 6f1c2a...
      bridgeos recordings download r1 6f1c2a... -o run.mcap
    """
    path = f"/api/robot/{url_path(robot, 'recordings', recording)}/download"
    with state().api().stream(path) as response:
        target = Path(output or attachment_name(response.headers.get("content-disposition")) or f"{recording}.mcap")
        total = int(response.headers["content-length"]) if "content-length" in response.headers else None
        partial = target.with_name(target.name + ".part")
        written = 0
        # Written beside the target and renamed at the end: an interrupted download leaves no half file under its name.
        bar: ProgressBar[int] = click.progressbar(
            length=total, label=target.name, file=sys.stderr, hidden=quiet or state().json
        )
        with partial.open("wb") as out, bar:
            for chunk in response.iter_bytes(CHUNK):
                out.write(chunk)
                written += len(chunk)
                bar.update(len(chunk))
        os.replace(partial, target)
    if state().json:
        emit_json({"file": str(target), "bytes": written})
    else:
        click.echo(f"{target} ({written} bytes)")


def attachment_name(disposition: str | None) -> str | None:
    """Return the file name of a Content-Disposition header, without any directory."""
    if not disposition or "filename=" not in disposition:
        return None
    name = disposition.split("filename=", 1)[1].split(";", 1)[0].strip().strip('"')
    return os.path.basename(name) or None
