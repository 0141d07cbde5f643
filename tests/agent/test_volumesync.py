"""Volume replicas on real directories: what a scan announces, what a receiver fetches, what it refuses."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import pytest

from bridgeos_agent.protocol import CHUNK_BYTES, VolumeChunks, VolumeFile
from bridgeos_agent.volumesync import MAX_HASHES_PER_FRAME, VolumeReplica, change_frames, receive_changes


def replica(tmp_path: Path, name: str) -> VolumeReplica:
    (tmp_path / name).mkdir(exist_ok=True)
    return VolumeReplica(tmp_path / name, tmp_path / f"{name}.index.json")


def sync(sender: VolumeReplica, receiver: VolumeReplica) -> list[list[dict]]:
    """Announce the sender's changes to the receiver; return the chunk requests it made."""
    asked: list[list[dict]] = []

    async def request(refs: list[dict]) -> VolumeChunks:
        asked.append(refs)
        found, missing = sender.read_chunks(refs)
        return VolumeChunks(skill="s", volume="data", chunks=found, missing=missing)

    changes = [VolumeFile(**change) for change in sender.scan()]
    asyncio.run(receive_changes(receiver, changes, request))
    return asked


def test_a_scan_announces_new_changed_and_deleted_files_but_not_touched_ones(tmp_path: Path) -> None:
    side = replica(tmp_path, "a")
    (side.root / "keep.txt").write_text("same")
    (side.root / "sub").mkdir()
    (side.root / "sub" / "gone.txt").write_text("bye")
    assert {c["path"] for c in side.scan()} == {"keep.txt", "sub/gone.txt"}
    assert side.scan() == []
    os.utime(side.root / "keep.txt", ns=(1, 1))  # touched, same content
    (side.root / "sub" / "gone.txt").unlink()
    (side.root / "new.bin").write_bytes(b"\0" * 10)
    changes = {c["path"]: c for c in side.scan()}
    assert set(changes) == {"sub/gone.txt", "new.bin"}
    assert changes["sub/gone.txt"] == {"path": "sub/gone.txt", "deleted": True}
    assert changes["new.bin"]["size"] == 10 and len(changes["new.bin"]["chunks"]) == 1


def test_a_receiver_fetches_only_the_chunks_it_does_not_hold(tmp_path: Path) -> None:
    robot, cloud = replica(tmp_path, "robot"), replica(tmp_path, "cloud")
    data = bytearray(os.urandom(6 * CHUNK_BYTES + 100))
    (robot.root / "map.bin").write_bytes(data)
    assert sum(len(refs) for refs in sync(robot, cloud)) == 7
    assert (cloud.root / "map.bin").read_bytes() == data

    data[3 * CHUNK_BYTES + 5] ^= 1
    (robot.root / "map.bin").write_bytes(data)
    (robot.root / "copy.bin").write_bytes(data)  # the same content again: nothing new to send
    asked = sync(robot, cloud)
    assert [ref["index"] for refs in asked for ref in refs] == [3]
    assert (cloud.root / "map.bin").read_bytes() == data == (cloud.root / "copy.bin").read_bytes()
    # What it wrote is in its index: its own next scan announces nothing back.
    assert cloud.scan() == []


def test_a_deletion_and_an_empty_file_arrive(tmp_path: Path) -> None:
    robot, cloud = replica(tmp_path, "robot"), replica(tmp_path, "cloud")
    (robot.root / "empty").write_bytes(b"")
    (robot.root / "doomed").write_text("x")
    sync(robot, cloud)
    assert (cloud.root / "empty").read_bytes() == b""
    (robot.root / "doomed").unlink()
    sync(robot, cloud)
    assert not (cloud.root / "doomed").exists() and cloud.scan() == []


def test_a_restarted_side_announces_only_what_changed_while_it_was_down(tmp_path: Path) -> None:
    side = replica(tmp_path, "a")
    (side.root / "one").write_text("1")
    side.scan()
    again = VolumeReplica(side.root, side.index_path)
    assert again.scan() == []
    (side.root / "one").write_text("2")
    assert [c["path"] for c in VolumeReplica(side.root, side.index_path).scan()] == ["one"]


def test_a_path_through_a_symlink_out_of_the_volume_is_refused(tmp_path: Path) -> None:
    cloud = replica(tmp_path, "cloud")
    outside = tmp_path / "outside"
    outside.mkdir()
    (cloud.root / "link").symlink_to(outside)
    change = VolumeFile(path="link/evil.txt", size=1, hash="0" * 64, chunks=[])
    with pytest.raises(ValueError, match="leaves the volume"):
        cloud.write(change, {})
    assert list(outside.iterdir()) == []
    assert cloud.read_chunks([{"path": "link/x", "index": 0, "hash": "0" * 64}]) == ([], ["0" * 64])


def test_content_that_does_not_match_its_hash_is_not_written(tmp_path: Path) -> None:
    robot, cloud = replica(tmp_path, "robot"), replica(tmp_path, "cloud")
    (robot.root / "f").write_text("real")
    announced = VolumeFile(**robot.scan()[0])
    with pytest.raises(ValueError, match="does not match"):
        cloud.write(announced, {announced.chunks[0]: b"fake"})
    assert not (cloud.root / "f").exists()
    assert [p.name for p in cloud.root.iterdir()] == []  # no temporary file left behind


def test_changes_are_split_into_frames_that_fit() -> None:
    big = {"path": "big", "chunks": ["a" * 64] * (MAX_HASHES_PER_FRAME - 10)}
    small = [{"path": f"f{n}", "chunks": ["b" * 64] * 20} for n in range(3)]
    assert [len(frame) for frame in change_frames([big, *small])] == [1, 3]
    deletions = [{"path": f"d{n}", "deleted": True} for n in range(2500)]
    assert [len(frame) for frame in change_frames(deletions)] == [1000, 1000, 500]
