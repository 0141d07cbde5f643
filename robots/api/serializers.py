"""Shapes of the Robot API's requests and answers about robots, tokens and commands."""

from __future__ import annotations

from rest_framework import serializers

from bridgeos_agent.skillconfig import SLUG_PATTERN
from skills.api.serializers import SkillSerializer
from skills.state import FLEET_FIELDS, ROBOT_FIELDS

from ..models import Robot


class AuthTokenSerializer(serializers.Serializer):
    token = serializers.CharField(help_text="Send as `Authorization: Token <token>`.")
    expires_at = serializers.DateTimeField()


class RenewedTokenSerializer(serializers.Serializer):
    expires_at = serializers.DateTimeField()


class RobotSerializer(serializers.ModelSerializer):
    """A robot with its skills and their components (the fields of `skills.state`, for the OpenAPI document)."""

    owner = serializers.CharField(source="owner.get_username", read_only=True)
    skills = SkillSerializer(many=True, read_only=True)

    class Meta:
        model = Robot
        fields = [*ROBOT_FIELDS, "skills"]
        read_only_fields = fields


class RobotCreateSerializer(serializers.Serializer):
    id = serializers.RegexField(SLUG_PATTERN, max_length=64, help_text="Slug: lowercase letters, digits, '-', '_'.")
    name = serializers.CharField(max_length=200, required=False, default="")
    config = serializers.JSONField(required=False, help_text="Robot config; defaults fill what is left out.")
    owner = serializers.CharField(required=False, help_text="Username of the owner (staff only; default: you).")

    def validate_id(self, value: str) -> str:
        # These would collide with the fleet-wide routes /api/robot/start|stop|shutdown.
        if value in {"start", "stop", "shutdown"}:
            raise serializers.ValidationError(f"{value!r} is reserved; choose another id.")
        return value


class RobotCreatedSerializer(RobotSerializer):
    token = serializers.CharField(help_text="The robot's token, shown only this once.")

    class Meta(RobotSerializer.Meta):
        fields = [*RobotSerializer.Meta.fields, "token"]
        read_only_fields = fields


class RobotUpdateSerializer(serializers.Serializer):
    name = serializers.CharField(max_length=200, required=False)
    config = serializers.JSONField(required=False, help_text="Replaces the whole robot config.")


class RobotTokenSerializer(serializers.Serializer):
    token = serializers.CharField(help_text="The new token, shown only this once; the old one stops working.")


class ReplySerializer(serializers.Serializer):
    event = serializers.CharField()
    data = serializers.JSONField()


class CommandResultSerializer(serializers.Serializer):
    robot = serializers.CharField()
    event = serializers.CharField()
    accepted = serializers.BooleanField(help_text="True when the robot acknowledged the command.")
    reply = ReplySerializer(help_text="The robot's answer: an `ack`, or an `error_message` saying why not.")


class FleetCommandResultSerializer(serializers.Serializer):
    robot = serializers.CharField()
    accepted = serializers.BooleanField()
    reply = ReplySerializer(required=False)
    error = serializers.CharField(required=False)


class FleetCommandSerializer(serializers.Serializer):
    results = FleetCommandResultSerializer(many=True)


class FleetQuerySerializer(serializers.Serializer):
    """GET /api/robot's optional page and fields; without them the answer is the whole fleet as before."""

    limit = serializers.IntegerField(min_value=1, max_value=1000, required=False, help_text="Robots per page.")
    offset = serializers.IntegerField(min_value=0, required=False, help_text="Robots to skip (by id order).")
    # Blank is let through to validate_fields, so `?fields=` is refused instead of ignored.
    fields = serializers.CharField(
        required=False, allow_blank=True, help_text=f"Comma-separated, of: {', '.join(FLEET_FIELDS)}. Default: all."
    )

    def validate_fields(self, value: str) -> list[str]:
        fields = [field.strip() for field in value.split(",")]
        unknown = [field for field in fields if field not in FLEET_FIELDS]
        if unknown:
            raise serializers.ValidationError(
                f"Unknown field(s): {', '.join(repr(f) for f in unknown)}; choose from {', '.join(FLEET_FIELDS)}."
            )
        return fields


class BridgeTicketSerializer(serializers.Serializer):
    ticket = serializers.CharField(help_text="Single use: spent by the first WebSocket that presents it.")
    expires_at = serializers.DateTimeField()
    rosbridge_url = serializers.CharField(help_text="rosbridge v2 WebSocket of the robot, with the ticket.")
    foxglove_url = serializers.CharField(help_text="Foxglove WebSocket of the robot, with the ticket.")
