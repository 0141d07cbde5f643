"""The ROS namespaces the Skill Router gives component instances."""

from __future__ import annotations

import re

import pytest
from pydantic import ValidationError

from bridgeos_agent.rosnames import canonical_name, graph_segment, instance_name, instance_namespace
from bridgeos_agent.skillconfig import parse_skill_config

# A ROS graph name segment as roscpp accepts it (ros::names::validate).
ROS_SEGMENT = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")


@pytest.mark.parametrize(
    ("slug", "segment"),
    [("people-detection", "people_detection"), ("mapping", "mapping"), ("3d-mapper", "n3d_mapper"), ("a_b", "a_b")],
)
def test_ids_become_valid_graph_name_segments(slug: str, segment: str) -> None:
    assert graph_segment(slug) == segment
    assert ROS_SEGMENT.match(segment)


def test_each_instance_gets_a_namespace_per_location() -> None:
    assert instance_namespace("people-detection", "sampler", "robot") == "/bridgeos/people_detection/sampler/robot"
    assert instance_namespace("people-detection", "sampler", "cloud") == "/bridgeos/people_detection/sampler/cloud"
    assert instance_name("points", "nav", "planner", "cloud") == "/bridgeos/nav/planner/cloud/points"
    assert canonical_name("points") == canonical_name("/points") == "/points"


def test_a_location_that_is_no_side_is_refused() -> None:
    with pytest.raises(ValueError, match="location"):
        instance_namespace("nav", "planner", "either")  # type: ignore[arg-type]


def test_a_skill_whose_component_ids_share_a_namespace_is_refused(sample) -> None:
    sample["components"]["sampl-er"] = sample["components"]["sampler"] | {"name": "Other sampler"}
    sample["components"]["sampl_er"] = sample["components"]["sampler"] | {"name": "Third sampler"}
    with pytest.raises(ValidationError, match="would share a ROS namespace"):
        parse_skill_config(sample)
