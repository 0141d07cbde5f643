"""Test the Skill configuration model, its JSON Schema and its field-level errors."""

from __future__ import annotations

import json
from typing import Any

import jsonschema
import pydantic
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bridgeos_agent.errors import NON_FIELD, field_errors
from bridgeos_agent.skillconfig import (
    SkillConfig,
    load_sample_skill_config,
    parse_skill_config,
    skill_config_json_schema,
)


def errors_of(data: Any) -> dict[str, list[str]]:
    """Parse data that must be invalid and return its field errors."""
    with pytest.raises(pydantic.ValidationError) as info:
        parse_skill_config(data)
    return field_errors(info.value)


def test_sample_parses_with_three_components(sample: dict[str, Any]) -> None:
    config = parse_skill_config(sample)
    assert config.skill_id == "people-detection"
    assert set(config.components) == {"pointcloud", "sampler", "detector"}
    assert config.components["pointcloud"].location == "robot"
    assert config.components["sampler"].robot is not None
    assert [t.name for t in config.router.topics] == ["/pointcloud", "/pointcloud_sampled", "/people"]


def test_packaged_sample_loads() -> None:
    assert load_sample_skill_config().skill == "People detection"


def test_parse_accepts_json_text_and_bytes(sample: dict[str, Any]) -> None:
    text = json.dumps(sample)
    assert parse_skill_config(text) == parse_skill_config(text.encode()) == parse_skill_config(sample)


def test_model_dump_round_trips(sample: dict[str, Any]) -> None:
    config = parse_skill_config(sample)
    assert parse_skill_config(config.model_dump()) == config
    assert parse_skill_config(config.model_dump_json()) == config


def test_minimal_config_gets_defaults() -> None:
    config = parse_skill_config(
        {
            "skill": "Echo",
            "skill_id": "echo",
            "components": {"echo": {"name": "Echo", "location": "robot", "robot": {"command": "echo hi"}}},
        }
    )
    assert config.manager.policy == "performance"
    assert config.manager.neural_network.hidden_layers == [16, 16]
    assert config.compose == {}
    assert config.components["echo"].robot is not None
    assert config.components["echo"].robot.command == ["echo", "hi"]


def test_sample_is_valid_against_exported_json_schema(sample: dict[str, Any]) -> None:
    schema = skill_config_json_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(sample, schema)
    assert schema["additionalProperties"] is False
    assert set(schema["required"]) == {"skill", "skill_id", "components"}


def test_negative_cpu_is_reported_at_its_path(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["resources"]["cpu"] = -1
    assert "components.detector.resources.cpu" in errors_of(sample)


def test_unknown_field_is_reported_as_unknown(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["resources"]["cpus"] = 2
    errors = errors_of(sample)
    assert errors["components.detector.resources.cpus"] == ["unknown field 'cpus'"]


def test_missing_required_field_is_reported(sample: dict[str, Any]) -> None:
    del sample["skill_id"]
    assert errors_of(sample)["skill_id"] == ["this field is required"]


def test_bad_skill_id_gets_a_human_hint(sample: dict[str, Any]) -> None:
    sample["skill_id"] = "People Detection"
    (message,) = errors_of(sample)["skill_id"]
    assert "lowercase" in message


def test_bad_component_id_is_reported_at_the_key(sample: dict[str, Any]) -> None:
    sample["components"]["Bad Id"] = sample["components"].pop("sampler")
    sample["router"]["topics"] = []
    (message,) = errors_of(sample)["components.Bad Id"]
    assert message.startswith("invalid key")


def test_bad_location_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["sampler"]["location"] = "moon"
    assert "components.sampler.location" in errors_of(sample)


def test_missing_launch_spec_for_location_is_reported(sample: dict[str, Any]) -> None:
    del sample["components"]["sampler"]["cloud"]
    errors = errors_of(sample)
    assert errors["components.sampler.cloud"] == ["location 'either' requires a 'cloud' launch spec"]


def test_launch_spec_without_image_or_command_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["pointcloud"]["robot"] = {"env": {}}
    assert "components.pointcloud.robot" in errors_of(sample)


def test_unsplittable_command_string_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["pointcloud"]["robot"]["command"] = 'python3 "unterminated'
    (message,) = errors_of(sample)["components.pointcloud.robot.command"]
    assert "quotation" in message


def test_duplicate_port_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["robot"]["ports"] = [8080, 8080]
    assert "components.detector.robot.ports" in errors_of(sample)


def test_bad_env_name_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["robot"]["env"] = {"1BAD": "x"}
    assert "components.detector.robot.env.1BAD" in errors_of(sample)


def test_bad_volume_name_is_reported(sample: dict[str, Any]) -> None:
    sample["volumes"] = ["ok-volume", "no spaces"]
    assert "volumes.1" in errors_of(sample)


def test_link_to_unknown_component_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["links"] = ["ghost"]
    assert errors_of(sample)["components.detector.links.0"] == ["unknown component 'ghost'"]


def test_self_link_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["links"] = ["sampler", "detector"]
    errors = errors_of(sample)
    assert list(errors) == ["components.detector.links.1"]
    assert "itself" in errors["components.detector.links.1"][0]


def test_robot_linked_to_cloud_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["location"] = "cloud"
    del sample["components"]["detector"]["robot"]
    sample["components"]["detector"]["links"] = ["pointcloud"]
    (message,) = errors_of(sample)["components.detector.links.0"]
    assert "share a location" in message


def test_robot_linked_to_either_is_allowed(sample: dict[str, Any]) -> None:
    sample["components"]["sampler"]["links"] = ["pointcloud"]
    config = parse_skill_config(sample)
    assert config.linked_components("pointcloud") == ["sampler"]


def test_robot_and_cloud_joined_through_either_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["location"] = "cloud"
    del sample["components"]["detector"]["robot"]
    sample["components"]["sampler"]["links"] = ["pointcloud", "detector"]
    errors = errors_of(sample)
    (path,) = errors
    assert path.startswith("components.") and path.endswith(".links")
    assert "never share a location" in errors[path][0]


def test_topic_publisher_must_be_a_component(sample: dict[str, Any]) -> None:
    sample["router"]["topics"][0]["publisher"] = "camera"
    assert errors_of(sample)["router.topics.0.publisher"] == ["unknown component 'camera'"]


def test_topic_subscriber_must_be_a_component(sample: dict[str, Any]) -> None:
    sample["router"]["topics"][1]["subscribers"] = ["detector", "ghost"]
    assert "router.topics.1.subscribers.1" in errors_of(sample)


def test_ros_topic_to_non_ros_component_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["ros"] = False
    errors = errors_of(sample)
    assert set(errors) == {"router.topics.1.subscribers.0", "router.topics.2.publisher"}


def test_service_server_must_be_a_component(sample: dict[str, Any]) -> None:
    sample["router"]["services"] = [{"name": "/detect", "type": "std_srvs/Trigger", "server": "nobody"}]
    assert "router.services.0.server" in errors_of(sample)


def test_http_route_component_must_exist(sample: dict[str, Any]) -> None:
    sample["router"]["http"][0]["component"] = "nobody"
    assert "router.http.0.component" in errors_of(sample)


def test_bad_topic_name_and_type_are_reported(sample: dict[str, Any]) -> None:
    sample["router"]["topics"][0]["name"] = "bad name"
    sample["router"]["topics"][0]["type"] = "PointCloud2"
    errors = errors_of(sample)
    assert {"router.topics.0.name", "router.topics.0.type"} <= set(errors)
    assert "ROS graph name" in errors["router.topics.0.name"][0]


def test_duplicate_topic_name_is_reported(sample: dict[str, Any]) -> None:
    sample["router"]["topics"][1]["name"] = "pointcloud"
    assert errors_of(sample)["router.topics.1.name"] == ["duplicate name 'pointcloud'"]


def test_duplicate_component_name_is_reported(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["name"] = "sampler"
    assert "components.detector.name" in errors_of(sample)


def test_custom_policy_requires_cost_functions(sample: dict[str, Any]) -> None:
    sample["manager"]["policy"] = "custom"
    sample["manager"]["cost_functions"] = {"robot": "cpu * 2"}
    errors = errors_of(sample)
    assert errors["manager.cost_functions"] == ["policy 'custom' needs a cost function for 'cloud'"]


def test_overlong_cost_function_is_reported(sample: dict[str, Any]) -> None:
    sample["manager"]["cost_functions"] = {"robot": "x" * 5000}
    assert "manager.cost_functions.robot" in errors_of(sample)


def test_unsafe_cost_function_is_reported_with_its_position(sample: dict[str, Any]) -> None:
    sample["manager"]["cost_functions"] = {"robot": "cpu.__class__", "cloud": "__import__('os')"}
    errors = errors_of(sample)
    assert errors["manager.cost_functions.robot"] == ["attribute access is not allowed at column 4"]
    assert "cannot call '__import__'" in errors["manager.cost_functions.cloud"][0]


def test_cost_function_may_read_resources_metrics_and_constants(sample: dict[str, Any]) -> None:
    sample["manager"]["policy"] = "custom"
    sample["manager"]["cost_functions"] = {
        "robot": "energy + latency * target_rate_hz",
        "cloud": "monetary if ros else cpu",
        "performance_cloud": "max(latency, 0.01)",
    }
    assert parse_skill_config(sample).manager.cost_functions["robot"].startswith("energy")


def test_cost_function_with_unknown_variable_or_key_is_reported(sample: dict[str, Any]) -> None:
    sample["manager"]["cost_functions"] = {"robot": "batery * 2", "energy_either": "1"}
    errors = errors_of(sample)
    assert errors["manager.cost_functions.robot"] == ["unknown name 'batery' at column 1"]
    assert "manager.cost_functions.energy_either" in errors


def test_constant_shadowing_a_cost_function_variable_is_reported(sample: dict[str, Any]) -> None:
    sample["manager"]["constants"] = {"cpu": 1.0}
    sample["manager"]["cost_functions"] = {"energy_robot": "cpu"}
    assert errors_of(sample)["manager.cost_functions"] == ["constants 'cpu' shadow built-in cost function variables"]


def test_neural_network_bounds_are_enforced(sample: dict[str, Any]) -> None:
    sample["manager"]["neural_network"]["hidden_layers"] = [0, 4096]
    sample["manager"]["neural_network"]["activation"] = "softmax"
    errors = errors_of(sample)
    assert {
        "manager.neural_network.hidden_layers.0",
        "manager.neural_network.hidden_layers.1",
        "manager.neural_network.activation",
    } <= set(errors)


def test_empty_components_is_reported(sample: dict[str, Any]) -> None:
    sample["components"] = {}
    sample["router"] = {}
    assert "components" in errors_of(sample)


def test_non_object_input_is_a_non_field_error() -> None:
    assert NON_FIELD in errors_of([1, 2, 3])


def test_malformed_json_is_a_validation_error() -> None:
    assert NON_FIELD in errors_of("{not json")


def test_field_errors_are_json_serialisable(sample: dict[str, Any]) -> None:
    sample["components"]["detector"]["links"] = ["ghost"]
    json.dumps(errors_of(sample))


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=12),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=20,
)
skill_keys = st.sampled_from(["skill", "skill_id", "volumes", "compose", "manager", "router", "components", "extra"])


@settings(max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(st.dictionaries(skill_keys | st.text(max_size=8), json_values, max_size=8))
def test_random_dicts_only_ever_raise_validation_error(data: dict[str, Any]) -> None:
    try:
        parse_skill_config(data)
    except pydantic.ValidationError as exc:
        assert isinstance(field_errors(exc), dict)


@settings(max_examples=200, suppress_health_check=[HealthCheck.too_slow])
@given(
    st.dictionaries(
        st.sampled_from(["name", "location", "links", "resources", "ros", "robot", "cloud"]),
        json_values | st.sampled_from(["robot", "cloud", "either"]),
    ),
    st.lists(st.sampled_from(["pointcloud", "sampler", "detector", "ghost"]), max_size=3),
)
def test_mutated_component_only_ever_raises_validation_error(component: dict[str, Any], links: list[str]) -> None:
    data = load_sample_skill_config().model_dump(mode="json")
    data["components"]["sampler"] = component
    data["components"]["detector"]["links"] = links
    try:
        config = parse_skill_config(data)
    except pydantic.ValidationError as exc:
        assert field_errors(exc)
    else:
        assert isinstance(config, SkillConfig)
