"""A robot's Skill volumes in the cloud stay under its quota: past it, changes are refused whole."""

from __future__ import annotations

import asyncio
import os
from pathlib import Path

import pytest
from django.contrib.auth import get_user_model
from rest_framework.test import APIClient

from bridgeos_agent.protocol import VolumeChanges, VolumeChunks
from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_agent.volumesync import VolumeReplica
from robots.consumers import connect_batch
from robots.models import Robot
from robots.services import Login, create_robot, issue_api_token
from skills.cloud.volumes import CloudVolumes, QuotaExceeded, volume_usage
from skills.services import add_skill

pytestmark = pytest.mark.django_db(transaction=True)

QUOTA = 1000


@pytest.fixture
def cloud_volumes(settings, tmp_path: Path) -> Path:
    """Keep the cloud's volumes in a temporary directory, with a 1000-byte quota per robot."""
    root = tmp_path / "cloud"
    settings.BRIDGEOS = {**settings.BRIDGEOS, "CLOUD_VOLUMES_DIR": str(root), "VOLUME_QUOTA_BYTES": QUOTA}
    return root


@pytest.fixture
def robot() -> str:
    owner = get_user_model().objects.create_user("quota-owner")
    robot, _ = create_robot("quota-bot", owner)
    config = {
        "skill": "Mapper",
        "skill_id": "mapper",
        "volumes": ["maps"],
        "components": {
            "m": {"name": "M", "location": "either", "robot": {"command": ["true"]}, "cloud": {"command": ["true"]}}
        },
    }
    add_skill(robot, parse_skill_config(config).model_dump(mode="json"))
    return robot.id


def sync(robot_side: VolumeReplica, robot_id: str) -> int:
    """Announce the robot replica's changes to the cloud and apply them there, as the consumer does."""
    changes = robot_side.scan()

    async def ask(data: dict) -> VolumeChunks:
        found, missing = robot_side.read_chunks(data["chunks"])
        return VolumeChunks(skill=data["skill"], volume=data["volume"], chunks=found, missing=missing)

    payload = VolumeChanges(skill="mapper", volume="maps", changes=changes)
    return asyncio.run(CloudVolumes(robot_id).receive(payload, ask))


def files(directory: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in directory.iterdir() if p.is_file()} if directory.exists() else {}


def test_changes_within_the_quota_are_stored_and_past_it_are_refused_whole(
    cloud_volumes: Path, robot: str, tmp_path: Path
) -> None:
    robot_side = VolumeReplica(tmp_path / "robot" / "maps", tmp_path / "robot.json")
    robot_side.root.mkdir(parents=True)
    (robot_side.root / "a.map").write_bytes(b"a" * 600)
    assert sync(robot_side, robot) == 1
    stored = cloud_volumes / robot / "mapper" / "maps"
    assert files(stored) == {"a.map": b"a" * 600}

    # 600 + 300 + 300 bytes would pass the 1000-byte quota: neither new file is stored.
    (robot_side.root / "b.map").write_bytes(b"b" * 300)
    (robot_side.root / "c.map").write_bytes(b"c" * 300)
    with pytest.raises(QuotaExceeded, match=r"over its quota of 1000 bytes .*nothing of them was stored") as refused:
        sync(robot_side, robot)
    assert refused.value.field == "data.changes"
    assert files(stored) == {"a.map": b"a" * 600}, "no partial files, no temporaries"
    assert sorted(os.listdir(stored)) == ["a.map"]
    assert volume_usage(robot) == {"mapper/maps": 600}


def test_shrinking_or_replacing_within_the_quota_is_always_allowed(
    cloud_volumes: Path, robot: str, tmp_path: Path
) -> None:
    robot_side = VolumeReplica(tmp_path / "robot" / "maps", tmp_path / "robot.json")
    robot_side.root.mkdir(parents=True)
    (robot_side.root / "a.map").write_bytes(b"a" * 900)
    sync(robot_side, robot)
    # A same-size rewrite at 90% of the quota, then a smaller one, then a deletion.
    (robot_side.root / "a.map").write_bytes(b"A" * 900)
    assert sync(robot_side, robot) == 1
    (robot_side.root / "a.map").write_bytes(b"x" * 10)
    sync(robot_side, robot)
    (robot_side.root / "a.map").unlink()
    sync(robot_side, robot)
    assert volume_usage(robot) == {"mapper/maps": 0}


def test_the_api_shows_a_robots_volume_usage_and_quota_to_its_owner_only(
    cloud_volumes: Path, robot: str, tmp_path: Path
) -> None:
    robot_side = VolumeReplica(tmp_path / "robot" / "maps", tmp_path / "robot.json")
    robot_side.root.mkdir(parents=True)
    (robot_side.root / "a.map").write_bytes(b"a" * 123)
    sync(robot_side, robot)
    owner = get_user_model().objects.get(username="quota-owner")
    client = APIClient()
    client.credentials(HTTP_AUTHORIZATION=f"Token {issue_api_token(owner)[0]}")
    answer = client.get(f"/api/robot/{robot}/volumes")
    assert answer.status_code == 200
    assert answer.json() == {"quota_bytes": QUOTA, "used_bytes": 123, "volumes": {"mapper/maps": 123}}
    stranger = get_user_model().objects.create_user("quota-stranger")
    client.credentials(HTTP_AUTHORIZATION=f"Token {issue_api_token(stranger)[0]}")
    assert client.get(f"/api/robot/{robot}/volumes").status_code == 404


def test_a_login_batch_says_which_robots_have_volumes_in_the_cloud(cloud_volumes: Path, robot: str) -> None:
    mapper = Robot.objects.get(id=robot)
    mapper_token = mapper.issue_token()
    mapper.save(update_fields=["token_hash", "previous_token_hash", "previous_token_until"])
    bare, bare_token = create_robot("quota-bare", mapper.owner)
    (cloud_volumes / robot / "mapper" / "maps").mkdir(parents=True)
    (cloud_volumes / "quota-file").write_bytes(b"")  # a file by a robot's name holds no volumes

    logins = [
        Login(robot_id, token, "127.0.0.1", f"channel-{robot_id}")
        for robot_id, token in [(robot, mapper_token), (bare.id, bare_token), ("quota-file", "not-a-token")]
    ]
    outcomes = connect_batch(logins)

    assert [(connected.robot, has_volumes) for connected, _, has_volumes in outcomes] == [
        (robot, True),
        (bare.id, False),
        (None, False),
    ]
