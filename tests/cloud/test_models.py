"""Models keep JSONB configs in PostgreSQL and refuse invalid ones with field errors."""

from __future__ import annotations

import copy
import io

import pytest
from django.contrib.auth import get_user_model
from django.core.exceptions import ValidationError
from django.core.management import CommandError, call_command
from django.db import connection

from bridgeos_agent.skillconfig import load_sample_skill_config
from robots.models import Robot
from robots.rotation import rotate_token
from robots.services import create_robot
from skills.models import Component, Skill, SkillTemplate
from skills.services import add_skill

pytestmark = pytest.mark.django_db


@pytest.fixture
def owner():
    return get_user_model().objects.create_user("owner", password="owner-pass-123")


@pytest.fixture
def sample_config() -> dict:
    return load_sample_skill_config().model_dump(mode="json")


def column_type(table: str, column: str) -> str:
    with connection.cursor() as cursor:
        cursor.execute(
            "SELECT data_type FROM information_schema.columns WHERE table_name = %s AND column_name = %s",
            [table, column],
        )
        return cursor.fetchone()[0]


def test_configs_are_stored_as_jsonb():
    assert column_type("robots_robot", "config") == "jsonb"
    assert column_type("skills_skill", "config") == "jsonb"
    assert column_type("skills_skilltemplate", "config") == "jsonb"
    assert column_type("monitoring_metric", "labels") == "jsonb"
    assert column_type("monitoring_event", "data") == "jsonb"


def test_metric_ts_has_a_brin_index():
    with connection.cursor() as cursor:
        cursor.execute("SELECT indexdef FROM pg_indexes WHERE indexname = 'metric_ts_brin'")
        assert "USING brin (ts)" in cursor.fetchone()[0]


def test_robot_config_round_trips_through_jsonb(owner):
    robot, _ = create_robot("r1", owner, config={"threshold": 0.8, "offloading": "manual", "resources": {"cpu": 4}})
    stored = Robot.objects.get(id="r1").config
    assert stored["threshold"] == 0.8
    assert stored["offloading"] == "manual"
    assert stored["resources"]["cpu"] == 4
    # Defaults are filled in, so the agent always receives a complete config.
    assert stored["heuristic"] == robot.config["heuristic"]
    # JSONB is queryable by key.
    assert Robot.objects.filter(config__offloading="manual").count() == 1


def test_invalid_robot_config_is_refused_with_field_errors_and_nothing_is_saved(owner):
    with pytest.raises(ValidationError) as excinfo:
        create_robot("r1", owner, config={"threshold": "high", "resources": {"cpu": -1}})
    messages = excinfo.value.message_dict["config"]
    assert any(message.startswith("threshold:") for message in messages)
    assert any(message.startswith("resources.cpu:") for message in messages)
    assert not Robot.objects.filter(id="r1").exists()


def test_robot_id_must_be_a_slug(owner):
    with pytest.raises(ValidationError) as excinfo:
        create_robot("Not A Slug", owner)
    assert "id" in excinfo.value.message_dict


def test_robot_token_is_stored_hashed(owner):
    robot, token = create_robot("r1", owner)
    robot.refresh_from_db()
    assert token not in robot.token_hash
    assert robot.check_token(token)
    assert not robot.check_token(token + "x")
    new_token = rotate_token(robot)
    robot.refresh_from_db()
    assert robot.check_token(new_token)
    assert not robot.check_token(token)


def test_skill_config_round_trips_and_creates_components(owner, sample_config):
    robot, _ = create_robot("r1", owner)
    skill = add_skill(robot, sample_config)
    stored = Skill.objects.get(pk=skill.pk)
    assert stored.config == sample_config
    assert stored.name == sample_config["skill"]
    components = {c.component_id: c for c in Component.objects.filter(skill=stored)}
    assert set(components) == set(sample_config["components"])
    for component_id, component in components.items():
        assert component.location == sample_config["components"][component_id]["location"]
        assert component.resources == sample_config["components"][component_id]["resources"]
    # Nested JSONB lookups reach into the config.
    assert Skill.objects.filter(config__components__pointcloud__location="robot").count() == 1


def test_invalid_skill_config_names_the_offending_field_and_adds_nothing(owner, sample_config):
    robot, _ = create_robot("r1", owner)
    bad = copy.deepcopy(sample_config)
    bad["components"]["sampler"]["resources"]["cpu"] = -2
    bad["components"]["sampler"]["locaton"] = "cloud"
    with pytest.raises(ValidationError) as excinfo:
        add_skill(robot, bad)
    messages = excinfo.value.message_dict["config"]
    assert any(m.startswith("components.sampler.resources.cpu:") for m in messages)
    assert any(m.startswith("components.sampler.locaton:") and "unknown field" in m for m in messages)
    assert not Skill.objects.exists()
    assert not Component.objects.exists()


def test_direct_save_cannot_store_an_invalid_config(owner, sample_config):
    robot, _ = create_robot("r1", owner)
    skill = Skill(robot=robot, skill_id="x", name="x", config={"skill": "x"})
    with pytest.raises(ValidationError):
        skill.save()
    assert not Skill.objects.exists()


def test_skill_template_validates_config_and_tags(sample_config):
    template = SkillTemplate.objects.create(name="People detection", config=sample_config, tags=["vision", "ros"])
    assert SkillTemplate.objects.get(pk=template.pk).config == sample_config
    with pytest.raises(ValidationError) as excinfo:
        SkillTemplate.objects.create(name="Bad", config=sample_config, tags="vision")
    assert "tags" in excinfo.value.message_dict


def test_create_robot_command_prints_the_token_once(owner):
    out, err = io.StringIO(), io.StringIO()
    call_command("create_robot", "cmd-bot", "--owner", "owner", stdout=out, stderr=err)
    token = out.getvalue().strip()
    assert token.startswith("brt_")
    assert Robot.objects.get(id="cmd-bot").check_token(token)
    assert "shown only once" in err.getvalue()
    with pytest.raises(CommandError, match="already exists"):
        call_command("create_robot", "cmd-bot", "--owner", "owner", stdout=io.StringIO(), stderr=io.StringIO())
    with pytest.raises(CommandError, match="No user named"):
        call_command("create_robot", "other", "--owner", "ghost", stdout=io.StringIO(), stderr=io.StringIO())
