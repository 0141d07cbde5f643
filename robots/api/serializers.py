"""Shapes of the Robot API's requests and answers about robots, tokens and commands."""

from __future__ import annotations

from django.core.exceptions import ValidationError as DjangoValidationError
from rest_framework import serializers

from bridgeos_agent.skillconfig import SLUG_PATTERN
from skills.api.serializers import SkillSerializer
from skills.state import FLEET_FIELDS, ROBOT_FIELDS

from .. import labels as robot_labels
from ..models import Robot

LABELS_HELP = (
    "Labels as key: value strings (keys: lowercase letters, digits, '-', '_', '.', at most 63; values the same "
    "with uppercase, may be empty; at most 64 labels)."
)


class LabelsField(serializers.DictField):
    """A robot's labels: checked by the rules of `robots.labels`, each problem naming its key."""

    child = serializers.CharField(allow_blank=True, trim_whitespace=False)

    def to_internal_value(self, data: object) -> dict[str, str]:
        try:
            return robot_labels.validate_labels(data)
        except DjangoValidationError as exc:
            raise serializers.ValidationError(exc.message_dict["labels"]) from None


class AuthTokenSerializer(serializers.Serializer):
    token = serializers.CharField(help_text="Send as `Authorization: Token <token>`.")
    expires_at = serializers.DateTimeField()


class RenewedTokenSerializer(serializers.Serializer):
    expires_at = serializers.DateTimeField()


class RobotSerializer(serializers.ModelSerializer):
    """A robot with its skills and their components (the fields of `skills.state`, for the OpenAPI document)."""

    owner = serializers.CharField(source="owner.get_username", read_only=True, allow_null=True)
    organization = serializers.CharField(source="organization.slug", read_only=True)
    labels = serializers.DictField(child=serializers.CharField(), read_only=True, help_text=LABELS_HELP)
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
    organization = serializers.CharField(
        required=False,
        max_length=64,
        help_text="Slug of the organization it joins, where you are admin (default: your token's, else your own).",
    )
    labels = LabelsField(required=False, help_text=LABELS_HELP)

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
    labels = LabelsField(required=False, help_text="Replaces all the robot's labels ({} removes them). " + LABELS_HELP)


class RobotTokenRotateSerializer(serializers.Serializer):
    grace_s = serializers.FloatField(
        required=False,
        default=0,
        min_value=0,
        max_value=30 * 86400,
        help_text="Seconds the old token keeps working, so robots re-key without a drop: a connected robot is "
        "given the new token over its connection at once (0: the old token stops at once, and the robot's live "
        "connection is closed).",
    )


class RobotTokenSerializer(serializers.Serializer):
    token = serializers.CharField(help_text="The new token, shown only this once.")
    old_token_valid_until = serializers.DateTimeField(
        allow_null=True, help_text="When the old token stops working; null: it already has."
    )


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
    selector = serializers.CharField(
        required=False,
        allow_blank=True,
        trim_whitespace=False,
        help_text="Only robots whose labels match, e.g. `site=lab,model!=x,gpu,!retired`: every comma-separated "
        "term must hold (`k=v` equal, `k!=v` not equal or absent, `k` has the key, `!k` lacks it).",
    )

    def validate_selector(self, value: str) -> robot_labels.Selector:
        try:
            return robot_labels.parse_selector(value)
        except DjangoValidationError as exc:
            raise serializers.ValidationError(exc.message_dict["selector"]) from None

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
