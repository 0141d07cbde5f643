"""Shapes of the Robot API's log queries and answers."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any

from django.utils.dateparse import parse_datetime
from rest_framework import serializers

from bridgeos_agent.protocol import LOG_LEVELS
from bridgeos_agent.skillconfig import SLUG_PATTERN

from ..choices import LOCATIONS
from ..services import decode_cursor, valid_regex

MAX_LIMIT = 1000


class TimeField(serializers.Field):
    """A time given as ISO 8601 (UTC when no zone is said) or as unix seconds."""

    default_error_messages = {"invalid": "An ISO 8601 time or unix seconds."}

    def to_internal_value(self, data: Any) -> datetime:
        text = str(data).strip()
        try:
            return datetime.fromtimestamp(float(text), UTC)
        except (ValueError, OverflowError, OSError):
            pass
        try:
            parsed = parse_datetime(text)
        except ValueError:
            parsed = None
        if parsed is None:
            self.fail("invalid")
        return parsed if parsed.tzinfo is not None else parsed.replace(tzinfo=UTC)

    def to_representation(self, value: datetime) -> str:
        return value.isoformat()


class LogQuerySerializer(serializers.Serializer):
    """The filters of a query of one robot's log; every one optional."""

    skill = serializers.RegexField(SLUG_PATTERN, max_length=64, required=False)
    component = serializers.RegexField(SLUG_PATTERN, max_length=64, required=False)
    location = serializers.ChoiceField(LOCATIONS, required=False)
    since = TimeField(required=False, help_text="ISO 8601 or unix seconds; lines at or after it.")
    until = TimeField(required=False, help_text="ISO 8601 or unix seconds; lines before it.")
    level = serializers.ChoiceField(LOG_LEVELS, required=False, help_text="Minimum level (no level counts as info).")
    q = serializers.CharField(max_length=1000, required=False, trim_whitespace=False, help_text="Substring, any case.")
    regex = serializers.BooleanField(required=False, default=False, help_text="`q` is a regular expression.")
    order = serializers.ChoiceField(["desc", "asc"], default="desc")
    limit = serializers.IntegerField(min_value=1, max_value=MAX_LIMIT, default=200)
    cursor = serializers.CharField(max_length=200, required=False)

    def validate_cursor(self, value: str) -> tuple[datetime, int]:
        try:
            return decode_cursor(value)
        except ValueError:
            raise serializers.ValidationError("Not a cursor of this API: use the `next` link of a page.") from None

    def validate(self, attrs: dict[str, Any]) -> dict[str, Any]:
        if attrs.get("since") and attrs.get("until") and attrs["since"] >= attrs["until"]:
            raise serializers.ValidationError({"since": ["Must be before `until`."]})
        if attrs.get("regex") and attrs.get("q"):
            problem = valid_regex(attrs["q"])
            if problem:
                raise serializers.ValidationError({"q": [problem]})
        return attrs


class LogLineSerializer(serializers.Serializer):
    skill = serializers.CharField()
    component = serializers.CharField()
    location = serializers.CharField()
    seq = serializers.IntegerField()
    ts = serializers.DateTimeField()
    stream = serializers.CharField()
    level = serializers.CharField(source="level_name", allow_null=True)
    text = serializers.CharField()


class LogPageSerializer(serializers.Serializer):
    results = LogLineSerializer(many=True)
    next = serializers.URLField(allow_null=True)
    dropped = serializers.IntegerField(help_text="Lines of the matching components their robot could not ship.")
