"""The cloud's side of Skill volume sync, for one robot's connection (see `bridgeos_agent.volumesync`).

The cloud keeps each robot's Skill volumes under BRIDGEOS_CLOUD_VOLUMES_DIR as
``<robot>/<skill>/<volume>/`` (bind-mounted into the cloud copies at /bridgeos/volumes/<volume>,
or named by BRIDGEOS_VOLUMES for processes) with their sync indexes in ``<robot>/.index/``.
The robot's consumer applies what the robot announces and, while any of the robot's volume
directories exists, scans them every second and announces the cloud copies' writes to the robot.

Quota: all of a robot's volumes together hold at most BRIDGEOS_VOLUME_QUOTA_MB in the cloud. A
robot's announcement that would grow them past it is refused whole, before any file is
written (``QuotaExceeded``); one that shrinks them or keeps their size is always applied.
"""

from __future__ import annotations

import asyncio
import logging
import os
from collections.abc import Awaitable, Callable, Iterable
from pathlib import Path
from typing import Any

from django.conf import settings

from bridgeos_agent.protocol import VolumeChanges, VolumeChunks, VolumeChunksGet
from bridgeos_agent.volumesync import VolumeReplica, change_frames, receive_changes
from bridgeos_cloud.errors import NotFound

from ..models import Skill
from .runtime import volumes_root

__all__ = ["CloudVolumes", "QuotaExceeded", "declared_volumes", "volume_growth", "volume_quota", "volume_usage"]

logger = logging.getLogger(__name__)

SCAN_INTERVAL = 1.0


def declared_volumes(robot_id: str, skill_id: str) -> list[str]:
    """Return the volumes a robot's Skill declares, or raise NotFound."""
    config = Skill.objects.filter(robot_id=robot_id, skill_id=skill_id).values_list("config", flat=True).first()
    if config is None:
        raise NotFound(f"robot {robot_id} has no skill {skill_id!r}", field="data.skill")
    return list(config.get("volumes") or [])


class QuotaExceeded(ValueError):
    """Volume changes would take a robot's cloud volumes past its quota: nothing of them is stored."""

    def __init__(self, message: str, *, field: str | None = None) -> None:
        super().__init__(message)
        self.message = message
        self.field = field


def volume_quota() -> int:
    """Return the bytes one robot's Skill volumes may hold in the cloud."""
    return int(settings.BRIDGEOS["VOLUME_QUOTA_BYTES"])


def volume_usage(robot_id: str) -> dict[str, int]:
    """Return the bytes each of a robot's cloud volumes holds now, as {"skill/volume": bytes}."""
    root = volumes_root() / robot_id
    usage: dict[str, int] = {}
    for skill_dir in _subdirs(root):
        if skill_dir.name.startswith("."):
            continue  # the sync indexes
        for volume_dir in _subdirs(skill_dir):
            usage[f"{skill_dir.name}/{volume_dir.name}"] = _bytes_under(volume_dir)
    return usage


def volume_growth(root: Path, changes: Iterable[Any]) -> int:
    """Return by how many bytes applying changes would grow the volume at ``root`` (negative: shrink)."""
    growth = 0
    for change in changes:
        try:
            now = (root / change.path).stat().st_size if (root / change.path).is_file() else 0
        except OSError:
            now = 0
        growth += -now if change.deleted else (change.size or 0) - now
    return growth


def robots_with_cloud_volumes(robot_ids: Iterable[str]) -> set[str]:
    """Return which of these robots have any volume in the cloud yet: one directory check each, for a login batch."""
    root = str(volumes_root())
    return {robot_id for robot_id in robot_ids if os.path.isdir(os.path.join(root, robot_id))}


class CloudVolumes:
    """One robot's cloud-side volume replicas."""

    def __init__(self, robot_id: str) -> None:
        self.robot_id = robot_id
        self.root = volumes_root() / robot_id
        self.replicas: dict[tuple[str, str], VolumeReplica] = {}
        # One announcement at a time is checked against the quota and applied: two at once could each fit alone.
        self._quota_lock = asyncio.Lock()

    def replica(self, skill_id: str, volume: str) -> VolumeReplica:
        """Return the replica of one of the robot's Skill volumes."""
        key = (skill_id, volume)
        if key not in self.replicas:
            self.replicas[key] = VolumeReplica(
                self.root / skill_id / volume, self.root / ".index" / skill_id / f"{volume}.json"
            )
        return self.replicas[key]

    async def receive(self, payload: VolumeChanges, ask: Callable[[dict[str, Any]], Awaitable[VolumeChunks]]) -> int:
        """Apply the robot's changes to the cloud copy of a volume it declares, asking it for missing chunks."""
        from channels.db import database_sync_to_async

        volumes = await database_sync_to_async(declared_volumes)(self.robot_id, payload.skill)
        if payload.volume not in volumes:
            raise NotFound(f"skill {payload.skill!r} declares no volume {payload.volume!r}", field="data.volume")
        replica = self.replica(payload.skill, payload.volume)

        async def request(refs: list[dict[str, Any]]) -> VolumeChunks:
            return await ask({"skill": payload.skill, "volume": payload.volume, "chunks": refs})

        async with self._quota_lock:
            await self._check_quota(replica.root, payload)
            await asyncio.to_thread(replica.root.mkdir, parents=True, exist_ok=True)
            return await receive_changes(replica, list(payload.changes), request)

    async def _check_quota(self, root: Path, payload: VolumeChanges) -> None:
        """Refuse changes that would grow the robot's volumes past its quota."""
        growth = await asyncio.to_thread(volume_growth, root, payload.changes)
        if growth <= 0:
            return  # shrinking (or same size) is always allowed, even over a lowered quota
        used = sum((await asyncio.to_thread(volume_usage, self.robot_id)).values())
        quota = volume_quota()
        if used + growth > quota:
            raise QuotaExceeded(
                f"volume {payload.skill}/{payload.volume}: these changes would bring robot {self.robot_id}'s "
                f"cloud volumes to {used + growth} bytes, over its quota of {quota} bytes "
                f"({used} used; BRIDGEOS_VOLUME_QUOTA_MB); nothing of them was stored",
                field="data.changes",
            )

    async def chunks(self, payload: VolumeChunksGet) -> dict[str, Any]:
        """Read chunks of a cloud volume the robot asks for."""
        replica = self.replica(payload.skill, payload.volume)
        refs = [ref.model_dump() for ref in payload.chunks]
        found, missing = await asyncio.to_thread(replica.read_chunks, refs)
        return {"skill": payload.skill, "volume": payload.volume, "chunks": found, "missing": missing}

    async def scan(self) -> list[dict[str, Any]]:
        """Return the data of volume_changes frames for every cloud volume of the robot that changed."""
        frames = []
        for skill_dir in await asyncio.to_thread(_subdirs, self.root):
            if skill_dir.name.startswith("."):
                continue
            for volume_dir in await asyncio.to_thread(_subdirs, skill_dir):
                replica = self.replica(skill_dir.name, volume_dir.name)
                changes = await asyncio.to_thread(replica.scan)
                for batch in change_frames(changes):
                    frames.append({"skill": skill_dir.name, "volume": volume_dir.name, "changes": batch})
        return frames


def _bytes_under(path: Path) -> int:
    total = 0
    for directory, _, files in os.walk(path, followlinks=False):
        for name in files:
            try:
                total += os.lstat(os.path.join(directory, name)).st_size
            except OSError:
                continue
    return total


def _subdirs(path: Path) -> list[Path]:
    try:
        return sorted(p for p in path.iterdir() if p.is_dir() and not p.is_symlink())
    except OSError:
        return []
