"""Shapes of the Robot API's requests and answers about skills, components and the catalog."""

from __future__ import annotations

from rest_framework import serializers

from bridgeos_agent.skillconfig import SLUG_PATTERN

from ..models import Component, Skill, SkillTemplate
from ..state import COMPONENT_FIELDS, SKILL_FIELDS


class ComponentSerializer(serializers.ModelSerializer):
    class Meta:
        model = Component
        fields = list(COMPONENT_FIELDS)
        read_only_fields = fields


class SkillSerializer(serializers.ModelSerializer):
    components = ComponentSerializer(many=True, read_only=True)

    class Meta:
        model = Skill
        fields = [*SKILL_FIELDS, "components"]
        read_only_fields = fields


class SkillDetailSerializer(SkillSerializer):
    robot = serializers.CharField(source="robot_id", read_only=True)

    class Meta(SkillSerializer.Meta):
        fields = ["robot", "skill_id", "name", "status", "config", "updated_at", "components"]
        read_only_fields = fields


class ComponentDetailSerializer(ComponentSerializer):
    robot = serializers.CharField(source="skill.robot_id", read_only=True)
    skill = serializers.CharField(source="skill.skill_id", read_only=True)
    config = serializers.SerializerMethodField()

    class Meta(ComponentSerializer.Meta):
        fields = ["robot", "skill", *ComponentSerializer.Meta.fields, "config"]
        read_only_fields = fields

    def get_config(self, component: Component) -> dict:
        """Return the component's part of the Skill config."""
        return component.skill.config["components"][component.component_id]


class SkillAddSerializer(serializers.Serializer):
    config = serializers.JSONField(required=False, help_text="A Skill config (thesis Table 4.1).")
    template = serializers.PrimaryKeyRelatedField(
        queryset=SkillTemplate.objects.all(), required=False, help_text="Id of a catalog template to add instead."
    )

    def validate(self, attrs: dict) -> dict:
        if ("config" in attrs) == ("template" in attrs):
            raise serializers.ValidationError("Give exactly one of `config` or `template`.")
        return attrs


class SkillRemoveSerializer(serializers.Serializer):
    skill = serializers.RegexField(SLUG_PATTERN, max_length=64)


class ComponentStartSerializer(serializers.Serializer):
    location = serializers.ChoiceField(["robot", "cloud"], help_text="Where to start the component.")


class ComponentStopSerializer(serializers.Serializer):
    location = serializers.ChoiceField(["robot", "cloud"], required=False, help_text="Which instance (default: all).")


class ComponentMigrateSerializer(serializers.Serializer):
    location = serializers.ChoiceField(
        ["robot", "cloud"], required=False, help_text="Target side (default: the other side of where it runs)."
    )


class SkillTemplateSerializer(serializers.ModelSerializer):
    organization = serializers.CharField(
        source="organization.slug",
        required=False,
        allow_null=True,
        max_length=64,
        help_text="Slug of the organization it belongs to (you must be a developer there); "
        "null: the cloud's catalog, which staff keep.",
    )

    class Meta:
        model = SkillTemplate
        fields = ["id", "organization", "name", "description", "tags", "config", "created_at"]
        read_only_fields = ["id", "created_at"]

    def get_validators(self) -> list:
        # A name is unique within its organization; the view checks that after the caller's rights,
        # so a name taken in another organization is never told.
        return []


class VolumeUsageSerializer(serializers.Serializer):
    """What a robot's Skill volumes hold in the cloud, against its quota."""

    quota_bytes = serializers.IntegerField(help_text="What all its volumes may hold (BRIDGEOS_VOLUME_QUOTA_MB).")
    used_bytes = serializers.IntegerField()
    volumes = serializers.DictField(child=serializers.IntegerField(), help_text='Bytes per "skill/volume".')
