"""Keep a Skill's volumes in step between the robot and the cloud (thesis §3.3.2), in content-hashed chunks.

Both sides hold a `VolumeReplica` per Skill volume: a directory and an index of what it last
saw there (size, mtime, SHA-256 of each 128 KiB chunk and of the whole file). Each side scans
its directory now and then and announces what changed since (`volume_changes`: paths with
their chunk hashes, or deletions; no data). The other side writes each announced file from
the chunks it already has anywhere in the volume (an edit in the middle of a large file costs
one chunk) and asks for the rest (`volume_chunks_get` → `volume_chunks`), then records the
file in its own index, so its next scan does not send it back. The last announcement applied
wins when both sides change one file between two scans.

The index is kept in a JSON file beside the volume, so a restarted side announces only what
really changed. Paths from the other side are checked to stay inside the volume (no "..",
no symlinked parents); temporary files are written beside their target and renamed over it.
"""

from __future__ import annotations

import base64
import contextlib
import hashlib
import json
import logging
import os
import stat
import tempfile
from collections.abc import Awaitable, Callable, Iterable, Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from bridgeos_agent.logonce import LogOnce
from bridgeos_agent.protocol import CHUNK_BYTES, MAX_CHUNKS_PER_FRAME, VolumeChunks, VolumeFile

if TYPE_CHECKING:
    from bridgeos_agent.hosts import SkillHost

__all__ = ["MAX_HASHES_PER_FRAME", "FileState", "VolumeReplica", "VolumeSync", "change_frames", "receive_changes"]

logger = logging.getLogger(__name__)

TEMP_PREFIX = ".bridgeos-sync-"
# Chunk hashes per volume_changes frame: ~70 bytes each keeps a frame well under 1 MiB.
MAX_HASHES_PER_FRAME = 8000
MAX_CHANGES_PER_FRAME = 1000

ChunkRequest = Callable[[list[dict[str, Any]]], Awaitable[VolumeChunks]]


@dataclass
class FileState:
    """What a replica knows of one file: enough to tell a change without reading it again."""

    size: int
    mtime_ns: int
    mode: int
    hash: str
    chunks: list[str] = field(default_factory=list)


def hash_file(path: Path) -> tuple[str, list[str], int]:
    """Return the SHA-256 of a file and of each of its chunks, and its size."""
    whole = hashlib.sha256()
    chunks = []
    size = 0
    with path.open("rb") as file:
        while block := file.read(CHUNK_BYTES):
            whole.update(block)
            chunks.append(hashlib.sha256(block).hexdigest())
            size += len(block)
    return whole.hexdigest(), chunks, size


class VolumeReplica:
    """One side's copy of one Skill volume: what it last saw, what it announces, what it applies."""

    def __init__(self, root: Path, index_path: Path) -> None:
        self.root = Path(root)
        self.index_path = Path(index_path)
        self.index: dict[str, FileState] = {}
        self._load()

    # --- announcing ----------------------------------------------------------------------

    def scan(self) -> list[dict[str, Any]]:
        """Return the files changed or deleted since the last scan (or apply), as VolumeFile data."""
        if not self.root.is_dir():
            return []
        seen: set[str] = set()
        changes: list[dict[str, Any]] = []
        for relative, info in self._walk():
            seen.add(relative)
            known = self.index.get(relative)
            mode = stat.S_IMODE(info.st_mode)
            if known is not None and known.size == info.st_size and known.mtime_ns == info.st_mtime_ns:
                continue
            try:
                digest, chunks, size = hash_file(self.root / relative)
            except OSError:
                continue  # vanished or unreadable mid-scan: the next scan sees it
            self.index[relative] = FileState(size, info.st_mtime_ns, mode, digest, chunks)
            if known is not None and known.hash == digest and known.mode == mode:
                continue  # touched, not changed
            if len(chunks) > MAX_HASHES_PER_FRAME:
                logger.warning("volume file %s is too large to sync (%d bytes)", self.root / relative, size)
                continue
            changes.append({"path": relative, "size": size, "mode": mode, "hash": digest, "chunks": chunks})
        for relative in sorted(set(self.index) - seen):
            del self.index[relative]
            changes.append({"path": relative, "deleted": True})
        if changes:
            self._save()
        return changes

    def read_chunks(self, refs: Iterable[dict[str, Any]]) -> tuple[list[dict[str, str]], list[str]]:
        """Return the requested chunks (base64) that are still there, and the hashes that are not."""
        found, missing = [], []
        for ref in refs:
            data = self._read_chunk(ref["path"], ref["index"], ref["hash"])
            if data is None:
                missing.append(ref["hash"])
            else:
                found.append({"hash": ref["hash"], "data": base64.b64encode(data).decode("ascii")})
        return found, missing

    # --- applying ------------------------------------------------------------------------

    def has(self, change: VolumeFile) -> bool:
        """Tell whether the file already holds exactly this content (then only the index learns of it)."""
        target = self._target(change.path)
        if target is None or not target.is_file():
            return False
        digest, chunks, size = hash_file(target)
        if digest != change.hash:
            return False
        info = target.stat()
        self.index[change.path] = FileState(size, info.st_mtime_ns, stat.S_IMODE(info.st_mode), digest, chunks)
        self._save()
        return True

    def needed(self, change: VolumeFile) -> tuple[list[dict[str, Any]], dict[str, bytes]]:
        """Split a file's chunks into those to ask for and those found locally (read now)."""
        local: dict[str, bytes] = {}
        wanted: list[dict[str, Any]] = []
        where = self._chunk_locations()
        for index, digest in enumerate(change.chunks):
            if digest in local:
                continue
            data = None
            if digest in where:
                data = self._read_chunk(*where[digest], digest)
            if data is None:
                if not any(ref["hash"] == digest for ref in wanted):
                    wanted.append({"path": change.path, "index": index, "hash": digest})
            else:
                local[digest] = data
        return wanted, local

    def write(self, change: VolumeFile, chunks: dict[str, bytes]) -> None:
        """Write a file from its chunks, atomically, and record it as seen."""
        target = self._target(change.path)
        if target is None:
            raise ValueError(f"volume path {change.path!r} leaves the volume")
        target.parent.mkdir(parents=True, exist_ok=True)
        if self._target(change.path) is None:
            raise ValueError(f"volume path {change.path!r} leaves the volume")
        whole = hashlib.sha256()
        fd, temp = tempfile.mkstemp(prefix=TEMP_PREFIX, dir=target.parent)
        try:
            with os.fdopen(fd, "wb") as out:
                for digest in change.chunks:
                    out.write(chunks[digest])
                    whole.update(chunks[digest])
            if whole.hexdigest() != change.hash:
                raise ValueError(f"volume file {change.path!r}: content does not match its announced hash")
            os.chmod(temp, change.mode)
            if target.is_dir() and not target.is_symlink():
                raise ValueError(f"volume path {change.path!r} is a directory here")
            os.replace(temp, target)
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(temp)
            raise
        info = target.stat()
        state = FileState(change.size, info.st_mtime_ns, change.mode, change.hash, list(change.chunks))
        self.index[change.path] = state
        self._save()

    def delete(self, path: str) -> None:
        """Delete a file the other side deleted, and forget it."""
        target = self._target(path)
        if target is not None and (target.is_file() or target.is_symlink()):
            with contextlib.suppress(FileNotFoundError):
                target.unlink()
        if self.index.pop(path, None) is not None:
            self._save()

    # --- inside ------------------------------------------------------------------------------

    def _walk(self) -> Iterator[tuple[str, os.stat_result]]:
        """Yield every regular file under the root (no symlinks, no sync temporaries)."""
        for directory, dirs, files in os.walk(self.root, followlinks=False):
            base = Path(directory)
            dirs[:] = sorted(d for d in dirs if not (base / d).is_symlink())
            for name in sorted(files):
                if name.startswith(TEMP_PREFIX):
                    continue
                path = base / name
                try:
                    info = path.lstat()
                except OSError:
                    continue
                if stat.S_ISREG(info.st_mode):
                    yield path.relative_to(self.root).as_posix(), info

    def _target(self, relative: str) -> Path | None:
        """Return where a path of the volume lives here, or None if it would leave the volume."""
        root = os.path.realpath(self.root)
        parent = os.path.realpath(os.path.dirname(os.path.join(root, relative)))
        if parent != root and not parent.startswith(root + os.sep):
            return None
        return Path(parent) / os.path.basename(relative)

    def _chunk_locations(self) -> dict[str, tuple[str, int]]:
        where: dict[str, tuple[str, int]] = {}
        for relative, state in self.index.items():
            for index, digest in enumerate(state.chunks):
                where.setdefault(digest, (relative, index))
        return where

    def _read_chunk(self, relative: str, index: int, digest: str) -> bytes | None:
        target = self._target(relative)
        if target is None:
            return None
        try:
            with target.open("rb") as file:
                file.seek(index * CHUNK_BYTES)
                data = file.read(CHUNK_BYTES)
        except OSError:
            return None
        return data if hashlib.sha256(data).hexdigest() == digest else None

    def _load(self) -> None:
        try:
            saved = json.loads(self.index_path.read_text())
            self.index = {path: FileState(**state) for path, state in saved.items()}
        except (OSError, ValueError, TypeError):
            self.index = {}

    def _save(self) -> None:
        self.index_path.parent.mkdir(parents=True, exist_ok=True)
        temp = self.index_path.with_suffix(".tmp")
        temp.write_text(json.dumps({path: asdict(state) for path, state in self.index.items()}))
        os.replace(temp, self.index_path)


def change_frames(changes: list[dict[str, Any]]) -> Iterator[list[dict[str, Any]]]:
    """Split announced changes into batches that each fit in one frame."""
    batch: list[dict[str, Any]] = []
    hashes = 0
    for change in changes:
        count = len(change.get("chunks", ()))
        if batch and (len(batch) >= MAX_CHANGES_PER_FRAME or hashes + count > MAX_HASHES_PER_FRAME):
            yield batch
            batch, hashes = [], 0
        batch.append(change)
        hashes += count
    if batch:
        yield batch


async def receive_changes(replica: VolumeReplica, changes: list[VolumeFile], request: ChunkRequest) -> int:
    """Apply announced changes, asking the sender for the chunks not found here; return files written."""
    import asyncio

    written = 0
    for change in changes:
        if change.deleted:
            await asyncio.to_thread(replica.delete, change.path)
            continue
        if change.hash is None or await asyncio.to_thread(replica.has, change):
            continue
        wanted, chunks = await asyncio.to_thread(replica.needed, change)
        complete = True
        for start in range(0, len(wanted), MAX_CHUNKS_PER_FRAME):
            reply = await request(wanted[start : start + MAX_CHUNKS_PER_FRAME])
            if reply.missing:
                complete = False  # the sender changed the file again; its next announcement carries it
                break
            for chunk in reply.chunks:
                data = base64.b64decode(chunk.data, validate=True)
                if hashlib.sha256(data).hexdigest() == chunk.hash:
                    chunks[chunk.hash] = data
        if complete and all(digest in chunks for digest in change.chunks):
            await asyncio.to_thread(replica.write, change, chunks)
            written += 1
    return written


class VolumeSync:
    """The robot's side: scan each running Skill's volumes, send what changed, apply what the cloud sends."""

    def __init__(self, host: SkillHost) -> None:
        self.host = host
        self.replicas: dict[tuple[str, str], VolumeReplica] = {}
        self._unreachable: set[tuple[str, str]] = set()
        self._failures: dict[tuple[str, str], LogOnce] = {}  # per volume: a scan failing every second is said once
        self.chunks_sent = 0  # chunks read for the cloud: what volume sync cost in data
        self._scanning: dict[tuple[str, str], Any] = {}  # one scan of a volume at a time (its index)

    async def run(self) -> None:
        """Scan the volumes of every running Skill that may have a cloud copy, for as long as the agent runs."""
        import asyncio

        interval = self.host.settings.volume_sync_interval
        if interval <= 0:
            return
        while True:
            await asyncio.sleep(interval)
            if not self.host.connected.is_set():
                continue  # nothing is lost: the next scan after reconnecting sees every change since
            for skill_id, record in list(self.host.skills.items()):
                if str(record.status) not in ("running", "starting") or not record.config.volumes:
                    continue
                if all(c.location == "robot" for c in record.config.components.values()):
                    continue
                for volume in record.config.volumes:
                    await self._sync(skill_id, volume)

    async def flush(self, skill_id: str) -> None:
        """Send a Skill's volume changes now: a cloud copy about to start reads them first."""
        record = self.host.skills.get(skill_id)
        if record is not None and self.host.settings.volume_sync_interval > 0:
            for volume in record.config.volumes:
                await self._sync(skill_id, volume)

    async def _sync(self, skill_id: str, volume: str) -> None:
        """Announce one volume's changes; a failure is said once until it syncs again, and retried next scan."""
        key = (skill_id, volume)
        try:
            await self.announce(skill_id, volume)
        except Exception as exc:
            # Any failure of one volume (disk, a file vanishing, the link) must not stop the others.
            self._failures.setdefault(key, LogOnce(logger, f"volume sync of {skill_id}/{volume}")).failed(exc)
        else:
            if key in self._failures:
                self._failures.pop(key).worked()

    async def announce(self, skill_id: str, volume: str) -> int:
        """Send one volume's changes since the last scan; return how many files changed."""
        import asyncio

        from bridgeos_agent.protocol import Event

        replica = await self.replica(skill_id, volume)
        if replica is None:
            return 0
        lock = self._scanning.setdefault((skill_id, volume), asyncio.Lock())
        async with lock:
            changes = await asyncio.to_thread(replica.scan)
            for batch in change_frames(changes):
                await self.host.emit(Event.VOLUME_CHANGES, {"skill": skill_id, "volume": volume, "changes": batch})
        return len(changes)

    async def receive(self, payload: Any) -> int:
        """Apply the cloud's changes to one of our volumes, fetching the chunks we lack."""
        from bridgeos_agent.protocol import Event, ProtocolError, parse_payload

        record = self.host.skills.get(payload.skill)
        if record is None or payload.volume not in record.config.volumes:
            raise ProtocolError(f"no volume {payload.volume!r} in skill {payload.skill!r} here", code="not_found")
        replica = await self.replica(payload.skill, payload.volume)
        if replica is None:
            raise ProtocolError(f"volume {payload.volume!r} cannot be reached on this robot", code="unavailable")

        async def request(refs: list[dict[str, Any]]) -> VolumeChunks:
            data = {"skill": payload.skill, "volume": payload.volume, "chunks": refs}
            reply = await self.host.request(Event.VOLUME_CHUNKS_GET, data, timeout=30.0)
            chunks = parse_payload(reply) if reply is not None and reply.event == Event.VOLUME_CHUNKS else None
            if not isinstance(chunks, VolumeChunks):
                raise ProtocolError("the cloud did not send the chunks asked for", code="unavailable")
            return chunks

        return await receive_changes(replica, list(payload.changes), request)

    async def chunks(self, payload: Any) -> dict[str, Any]:
        """Read chunks the cloud asks for."""
        import asyncio

        replica = await self.replica(payload.skill, payload.volume)
        refs = [ref.model_dump() for ref in payload.chunks]
        found, missing = (
            await asyncio.to_thread(replica.read_chunks, refs) if replica else ([], [r["hash"] for r in refs])
        )
        self.chunks_sent += len(found)
        return {"skill": payload.skill, "volume": payload.volume, "chunks": found, "missing": missing}

    async def replica(self, skill_id: str, volume: str) -> VolumeReplica | None:
        """Return the replica of one of a Skill's volumes, where the robot's runtime keeps it."""
        key = (skill_id, volume)
        replica = self.replicas.get(key)
        if replica is None:
            root = await local_volume_path(self.host.runtime, skill_id, volume)
            if root is None:
                if key not in self._unreachable:
                    self._unreachable.add(key)
                    self.host.say(f"volume {skill_id}/{volume}: not readable here; it is not synced")
                return None
            index = self.host.data_dir / "volumesync" / skill_id / f"{volume}.json"
            replica = self.replicas[key] = VolumeReplica(root, index)
        return replica


async def local_volume_path(runtime: Any, skill_id: str, volume: str) -> Path | None:
    """Return the directory a robot runtime keeps a Skill volume in, if this process can read it."""
    import asyncio

    if hasattr(runtime, "volumes_dir"):
        return Path(runtime.volumes_dir(skill_id)) / volume
    if hasattr(runtime, "volume_name"):
        # A Docker volume: its mountpoint on this host (readable as root).
        def mountpoint() -> Path | None:
            import docker.client
            import docker.errors

            try:
                client = docker.client.from_env()
                path = client.api.inspect_volume(runtime.volume_name(skill_id, volume))["Mountpoint"]
            except (docker.errors.DockerException, OSError, KeyError) as exc:
                logger.debug("volume %s/%s: no Docker mountpoint: %s", skill_id, volume, exc)
                return None
            return Path(path) if os.access(path, os.R_OK | os.W_OK) else None

        return await asyncio.to_thread(mountpoint)
    return None
