"""Test the robot configuration model, its defaults and its field-level errors."""

from __future__ import annotations

import json
import typing
from typing import Any

import jsonschema
import pydantic
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from bridgeos_agent.errors import field_errors
from bridgeos_agent.robotconfig import (
    Heuristic,
    RobotConfig,
    parse_robot_config,
    robot_config_json_schema,
)


def errors_of(data: Any) -> dict[str, list[str]]:
    """Parse data that must be invalid and return its field errors."""
    with pytest.raises(pydantic.ValidationError) as info:
        parse_robot_config(data)
    return field_errors(info.value)


def test_default_config_is_valid() -> None:
    config = RobotConfig()
    assert config.heuristic == "resource_usage"
    assert config.offloading == "auto"
    assert config.subnets is None
    assert parse_robot_config({}) == config


def test_all_five_thesis_heuristics_are_offered() -> None:
    assert set(typing.get_args(Heuristic)) == {
        "resource_usage",
        "migration_cost",
        "resource_expenditure",
        "temporal_cost",
        "weighted_cost",
    }


def test_full_config_parses_and_round_trips() -> None:
    data = {
        "resources": {"cpu": 4, "gpu": 1, "ram": 8192, "bandwidth": 54, "io": 200, "battery": 98.5},
        "heuristic": "weighted_cost",
        "threshold": 2.5,
        "weights": {"gain": 1, "cost": 0.5, "loss": 0.2, "time": 2},
        "offloading": "manual",
        "subnets": {"local": "10.8.1.0/24", "cloud": "10.9.1.0/24"},
        "energy": {"cpu": 12, "wifi": 3},
        "costs": {"per_gb": 0.05, "per_kwh": 0.3, "cloud": {"cpu": 0.04}},
        "heartbeat_interval": 2,
        "connection_lost_after": 10,
    }
    config = parse_robot_config(data)
    assert config.resources.battery == 98.5
    assert parse_robot_config(config.model_dump()) == config
    assert parse_robot_config(config.model_dump_json()) == config
    assert parse_robot_config(json.dumps(data).encode()) == config


def test_defaults_are_valid_against_exported_json_schema() -> None:
    schema = robot_config_json_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(RobotConfig().model_dump(mode="json"), schema)
    jsonschema.validate({}, schema)


def test_unknown_heuristic_is_reported() -> None:
    assert "heuristic" in errors_of({"heuristic": "greedy"})


def test_unknown_offloading_mode_is_reported() -> None:
    assert "offloading" in errors_of({"offloading": "dynamic"})


def test_negative_resource_is_reported() -> None:
    assert "resources.ram" in errors_of({"resources": {"ram": -1}})


def test_typo_is_reported_as_unknown_field() -> None:
    assert errors_of({"resources": {"cpus": 2}})["resources.cpus"] == ["unknown field 'cpus'"]


def test_bad_cidr_is_reported() -> None:
    errors = errors_of({"subnets": {"local": "10.8.1.0/33", "cloud": "10.9.1.1/24"}})
    assert {"subnets.local", "subnets.cloud"} <= set(errors)


def test_overlapping_subnets_are_reported() -> None:
    errors = errors_of({"subnets": {"local": "10.8.0.0/16", "cloud": "10.8.1.0/24"}})
    assert list(errors) == ["subnets.cloud"]


def test_subnets_are_normalised() -> None:
    config = parse_robot_config({"subnets": {"local": "fd00::/64", "cloud": "10.9.1.0/24"}})
    assert config.subnets is not None
    assert config.subnets.local == "fd00::/64"


def test_connection_lost_must_outlast_heartbeat() -> None:
    errors = errors_of({"heartbeat_interval": 10, "connection_lost_after": 5})
    assert list(errors) == ["connection_lost_after"]


def test_non_finite_threshold_is_reported() -> None:
    assert "threshold" in errors_of('{"threshold": Infinity}') or "__all__" in errors_of('{"threshold": Infinity}')
    assert "threshold" in errors_of({"threshold": float("nan")})


def test_bad_energy_key_is_reported() -> None:
    assert "energy.2cpu" in errors_of({"energy": {"2cpu": 1}})


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=20,
)


@settings(max_examples=200)
@given(st.dictionaries(st.sampled_from(list(RobotConfig.model_fields)) | st.text(max_size=8), json_values, max_size=6))
def test_random_dicts_only_ever_raise_validation_error(data: dict[str, Any]) -> None:
    try:
        parse_robot_config(data)
    except pydantic.ValidationError as exc:
        assert field_errors(exc)
