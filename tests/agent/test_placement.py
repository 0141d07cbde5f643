"""The agent's location rules, defined once in placement: where a component may start, where a move goes."""

from __future__ import annotations

import pytest

from bridgeos_agent.placement import check_location, migration_target
from bridgeos_agent.protocol import ProtocolError


def test_a_robot_only_component_may_not_start_in_the_cloud() -> None:
    with pytest.raises(ProtocolError, match="may only run on the robot") as refused:
        check_location("lidar", "robot", "cloud")
    assert refused.value.field == "data.location"


def test_a_cloud_only_component_may_not_start_on_the_robot() -> None:
    with pytest.raises(ProtocolError, match="may only run in the cloud"):
        check_location("uploader", "cloud", "robot")


@pytest.mark.parametrize(("required", "location"), [("either", "robot"), ("either", "cloud"), ("robot", "robot")])
def test_allowed_locations_pass(required: str, location: str) -> None:
    check_location("c", required, location)


def test_a_migration_without_a_target_goes_to_the_other_side() -> None:
    assert migration_target("c", "either", "robot", None) == "cloud"
    assert migration_target("c", "either", "cloud", None) == "robot"
    assert migration_target("c", "either", None, None) == "cloud"
    assert migration_target("c", "either", "robot", "robot") == "robot"


def test_a_component_pinned_to_one_side_does_not_migrate() -> None:
    with pytest.raises(ProtocolError, match="may only run on the robot") as refused:
        migration_target("lidar", "robot", "robot", "cloud")
    assert refused.value.field == "data.component"
