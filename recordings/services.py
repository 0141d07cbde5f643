"""Domain actions on recordings: start and stop them on the robot, keep their chunks, assemble the file."""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asgiref.sync import async_to_sync
from django.conf import settings
from django.db import transaction
from django.db.models import QuerySet

from bridgeos_agent.protocol import Event
from bridgeos_agent.protocol import RecordingStatus as StatusReport
from bridgeos_cloud.errors import NotFound
from monitoring.choices import Level
from monitoring.services import record_event
from robots import services as robots
from robots.models import Robot

from .choices import RUNNING, RecordingStatus
from .models import Recording

__all__ = [
    "RecordingRefused",
    "delete_recording",
    "recordings_of",
    "remove_files",
    "report_recording_status",
    "salvage_mcap",
    "start_recording",
    "stop_recording",
    "store_recording_chunk",
]

log = logging.getLogger(__name__)

DEFAULT_MAX_BYTES = 100 * 1024 * 1024
DEFAULT_MAX_DURATION_S = 600.0


class RecordingRefused(Exception):
    """A request about a recording that cannot be carried out; ``field`` names what is wrong."""

    def __init__(self, message: str, *, field: str = "non_field_errors") -> None:
        super().__init__(message)
        self.message = message
        self.field = field


def recordings_of(robot: Robot) -> QuerySet[Recording]:
    """Return a robot's recordings, newest first."""
    return Recording.objects.filter(robot=robot)


def _open(robot: Robot, topics: list[str], ros: str, max_bytes: int, max_duration_s: float) -> Recording:
    """Add a recording in state starting, unless the robot runs one already."""
    with transaction.atomic():
        # Locked, so two starts at once cannot both find the robot idle.
        Robot.objects.select_for_update().filter(id=robot.id).first()
        running = Recording.objects.filter(robot=robot, status__in=RUNNING).first()
        if running is not None:
            raise RecordingRefused(f"recording {running.id} is already running on this robot; stop it first")
        return Recording.objects.create(
            robot=robot, topics=topics, ros=ros, max_bytes=max_bytes, max_duration_s=max_duration_s
        )


def start_recording(
    robot: Robot,
    *,
    topics: list[str],
    ros: str | None = None,
    max_bytes: int = DEFAULT_MAX_BYTES,
    max_duration_s: float = DEFAULT_MAX_DURATION_S,
    wait: float = 5.0,
) -> Recording:
    """Ask the robot to record; a refusal (unknown topic, no such graph) leaves no recording behind.

    Raises RecordingRefused, robots.services.RobotOffline (nothing kept) and CommandTimeout (the
    recording is kept as starting: the robot gets the order when it answers again).
    """
    recording = _open(robot, topics, ros or "", max_bytes, max_duration_s)
    order: dict[str, Any] = {
        "recording": recording.id.hex,
        "topics": topics,
        "max_bytes": max_bytes,
        "max_duration_s": max_duration_s,
    }
    if ros:
        order["ros"] = ros
    try:
        reply = async_to_sync(robots.relay_command)(robot.id, Event.RECORDING_START, order, wait=wait)
    except robots.RobotOffline:
        recording.delete()
        raise
    if reply.event == Event.ERROR_MESSAGE:
        recording.delete()
        field = str(reply.data.get("field") or "")
        raise RecordingRefused(
            str(reply.data.get("message", "refused by the robot")),
            field=field.removeprefix("data.") if field.startswith("data.") else "non_field_errors",
        )
    record_event(
        f"Recording {recording.id.hex} of {', '.join(topics)} started on robot {robot.id}",
        robot_id=robot.id,
        kind="recording_started",
        data={"recording": recording.id.hex, "topics": topics},
    )
    return recording


def stop_recording(recording: Recording, *, wait: float = 5.0) -> Recording:
    """Ask the robot to end a running recording; its last chunks and totals follow."""
    if not recording.running:
        raise RecordingRefused(f"recording {recording.id} is {recording.status}, not running", field="status")
    reply = async_to_sync(robots.relay_command)(
        recording.robot_id, Event.RECORDING_STOP, {"recording": recording.id.hex}, wait=wait
    )
    with transaction.atomic():
        recording = Recording.objects.select_for_update().get(pk=recording.pk)
        if reply.event == Event.ERROR_MESSAGE:
            # The robot no longer has it (its agent restarted): what arrived is all there will be.
            recording.status, recording.outcome = RecordingStatus.FAILED, RecordingStatus.FAILED
            recording.message = str(reply.data.get("message", "the robot refused to stop it"))[:2000]
            recording.save(update_fields=["status", "outcome", "message"])
        elif recording.running:
            recording.status = RecordingStatus.STOPPING
            recording.save(update_fields=["status"])
    return recording


def delete_recording(recording: Recording) -> None:
    """Delete a recording and its file; a running one must be stopped first."""
    if recording.running:
        raise RecordingRefused(f"recording {recording.id} is {recording.status}; stop it first", field="status")
    recording.delete()  # remove_files takes its files once the deletion is committed


def remove_files(sender: type[Recording], instance: Recording, **_: Any) -> None:
    """Remove a deleted recording's chunks and file once the deletion is committed (post_delete)."""
    folder = instance.folder

    def remove() -> None:
        shutil.rmtree(folder, ignore_errors=True)
        with contextlib.suppress(OSError):
            folder.parent.rmdir()  # the robot's folder, once its last recording went

    transaction.on_commit(remove)


# --------------------------------------------------------------------------- what robots send


def _robots_recording(robot_id: str, recording_id: str, *, lock: bool = False) -> Recording:
    rows = Recording.objects.select_for_update() if lock else Recording.objects
    recording = rows.filter(robot_id=robot_id, id=recording_id).first()
    if recording is None:
        raise NotFound(f"no recording {recording_id} of this robot in the cloud", field="recording")
    return recording


def _chunk_path(folder: Path, seq: int) -> Path:
    return folder / "chunks" / f"{seq:08d}.part"


def store_recording_chunk(robot_id: str, recording_id: str, seq: int, data: bytes) -> None:
    """Keep one chunk of a recording (a chunk sent twice is written twice, the same); assemble when complete."""
    recording = _robots_recording(robot_id, recording_id)
    path = _chunk_path(recording.folder, seq)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(".tmp")
    partial.write_bytes(data)
    os.replace(partial, path)  # whole or absent, never half a chunk
    if recording.chunks is not None:
        with transaction.atomic():
            _assemble(_robots_recording(robot_id, recording_id, lock=True))


def report_recording_status(robot_id: str, report: StatusReport) -> None:
    """Apply what the robot says of a recording: it runs, or it ended with its totals."""
    with transaction.atomic():
        recording = _robots_recording(robot_id, report.recording, lock=True)
        if report.ros:
            recording.ros = report.ros
        if report.started_at is not None:
            recording.started_at = datetime.fromtimestamp(report.started_at, tz=UTC)
        if report.status == RecordingStatus.RECORDING:
            if recording.status == RecordingStatus.STARTING:
                recording.status = RecordingStatus.RECORDING
        elif report.status in (RecordingStatus.FINISHED, RecordingStatus.FAILED) and recording.chunks is None:
            recording.outcome = report.status
            recording.message = report.message or ""
            recording.chunks = report.chunks or 0
            recording.message_count, recording.data_bytes = report.messages, report.bytes
            if report.stopped_at is not None:
                recording.stopped_at = datetime.fromtimestamp(report.stopped_at, tz=UTC)
                if report.started_at is not None:
                    recording.duration_s = max(0.0, report.stopped_at - report.started_at)
            if recording.status in RUNNING:
                recording.status = RecordingStatus.STOPPING  # until every chunk is in
        recording.save()
        _assemble(recording)


def _assemble(recording: Recording) -> None:
    """Join a recording's chunks into its .mcap file once the robot said how many and all arrived."""
    if recording.chunks is None or recording.file or recording.status != RecordingStatus.STOPPING:
        return
    folder = recording.folder
    parts = [_chunk_path(folder, seq) for seq in range(recording.chunks)]
    if not all(part.exists() for part in parts):
        return  # the others are on their way (or in the robot's outbox until it reconnects)
    target = folder / "recording.mcap"
    partial = target.with_suffix(".tmp")
    with partial.open("wb") as out:
        for part in parts:
            with part.open("rb") as chunk:
                shutil.copyfileobj(chunk, out)
    os.replace(partial, target)
    salvaged = salvage_mcap(target)
    if salvaged is not None:
        # Cut short (the robot's agent died mid-recording): the totals are what the file holds.
        recording.message_count, recording.data_bytes, duration = salvaged
        if duration is not None:
            recording.duration_s = duration
    shutil.rmtree(folder / "chunks", ignore_errors=True)
    recording.file = str(target.relative_to(settings.BRIDGEOS["RECORDINGS_DIR"]))
    recording.size_bytes = target.stat().st_size
    recording.status = recording.outcome or RecordingStatus.FINISHED
    recording.save(update_fields=["file", "size_bytes", "status", "message_count", "data_bytes", "duration_s"])
    record_event(
        f"Recording {recording.id.hex} of robot {recording.robot_id} {recording.status}: "
        f"{recording.message_count} message(s), {recording.size_bytes} bytes ({recording.message or 'ended'})",
        robot_id=recording.robot_id,
        level=Level.INFO if recording.status == RecordingStatus.FINISHED else Level.WARNING,
        kind="recording_finished",
        data={"recording": recording.id.hex, "messages": recording.message_count, "bytes": recording.size_bytes},
    )


MCAP_MAGIC = b"\x89MCAP0\r\n"


def salvage_mcap(path: Path) -> tuple[int, int, float | None] | None:
    """Rewrite a cut-off MCAP file whole from its complete records; None if it was whole already.

    Returns the messages kept, their bytes and the seconds between the first and the last.
    """
    from mcap.records import Channel, Header, Message, Schema
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, Writer

    with path.open("rb") as file:
        file.seek(max(0, path.stat().st_size - len(MCAP_MAGIC)))
        if file.read() == MCAP_MAGIC:
            return None
    partial = path.with_suffix(".salvage")
    messages = data_bytes = 0
    first = last = None
    with path.open("rb") as source, partial.open("wb") as out:
        writer = Writer(out, compression=CompressionType.ZSTD)
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        started = False
        try:
            for record in StreamReader(source).records:
                if isinstance(record, Header) and not started:
                    writer.start(profile=record.profile, library=record.library or "bridgeos-cloud salvage")
                    started = True
                elif isinstance(record, Schema) and record.id not in schemas:
                    schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
                elif isinstance(record, Channel) and record.id not in channels and record.schema_id in schemas:
                    channels[record.id] = writer.register_channel(
                        record.topic, record.message_encoding, schemas[record.schema_id], record.metadata
                    )
                elif isinstance(record, Message) and record.channel_id in channels:
                    writer.add_message(
                        channels[record.channel_id], record.log_time, record.data, record.publish_time, record.sequence
                    )
                    messages += 1
                    data_bytes += len(record.data)
                    first = record.log_time if first is None else min(first, record.log_time)
                    last = record.log_time if last is None else max(last, record.log_time)
        except Exception:
            log.info("recording %s: kept %d message(s) before the cut", path.parent.name, messages)
        if not started:
            writer.start(profile="", library="bridgeos-cloud salvage")
        writer.finish()
    os.replace(partial, path)
    duration = (last - first) / 1e9 if first is not None and last is not None else None
    return messages, data_bytes, duration
