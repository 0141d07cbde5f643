"""Shapes of the Robot API's monitoring requests and answers."""

from __future__ import annotations

from datetime import timedelta

from django.utils import timezone
from rest_framework import serializers

from bridgeos_agent.skillconfig import SLUG_PATTERN

from ..choices import Level
from ..models import Event
from ..services import AGGREGATES

slug = serializers.RegexField(SLUG_PATTERN, max_length=64)
MAX_RANGE = timedelta(days=366)


class QuerySerializer(serializers.Serializer):
    """A structured query of metrics or of the event log; no SQL ever comes from the client."""

    kind = serializers.ChoiceField(["metrics", "events"], default="metrics")
    robots = serializers.ListField(child=slug, max_length=1000, required=False, help_text="Default: all yours.")
    skill = serializers.RegexField(SLUG_PATTERN, max_length=64, required=False)
    component = serializers.RegexField(SLUG_PATTERN, max_length=64, required=False)
    names = serializers.ListField(child=serializers.CharField(max_length=128), max_length=100, required=False)
    since = serializers.DateTimeField(required=False, help_text="Default: an hour before `until`.")
    until = serializers.DateTimeField(required=False, help_text="Default: now.")
    aggregate = serializers.ChoiceField(sorted(AGGREGATES), default="avg")
    bucket = serializers.IntegerField(min_value=1, max_value=86_400, required=False, help_text="Seconds per bucket.")
    level = serializers.ChoiceField(Level.choices, required=False, help_text="Events only: minimum level.")
    limit = serializers.IntegerField(min_value=1, max_value=10_000, default=1000)

    def validate(self, attrs: dict) -> dict:
        attrs.setdefault("until", timezone.now())
        attrs.setdefault("since", attrs["until"] - timedelta(hours=1))
        if attrs["since"] >= attrs["until"]:
            raise serializers.ValidationError({"since": ["Must be before `until`."]})
        if attrs["until"] - attrs["since"] > MAX_RANGE:
            raise serializers.ValidationError({"since": ["A query spans at most a year."]})
        return attrs


class MetricRowSerializer(serializers.Serializer):
    robot = serializers.CharField()
    skill = serializers.CharField()
    component = serializers.CharField()
    name = serializers.CharField()
    bucket = serializers.DateTimeField(help_text="Start of the bucket (or of the range's first point).")
    value = serializers.FloatField()
    points = serializers.IntegerField(help_text="How many points were aggregated.")


class EventSerializer(serializers.ModelSerializer):
    robot = serializers.CharField(source="robot_id", allow_null=True)

    class Meta:
        model = Event
        fields = ["id", "ts", "level", "source", "kind", "robot", "skill", "component", "message", "data"]
        read_only_fields = fields


class QueryResultSerializer(serializers.Serializer):
    kind = serializers.CharField()
    results = serializers.ListField(child=serializers.DictField())
