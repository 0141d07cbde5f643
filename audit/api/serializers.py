"""Serializers of the audit API: the query's filters and an entry."""

from __future__ import annotations

from typing import Any

from django.db.models import Q, QuerySet
from rest_framework import serializers

from ..choices import Door, Outcome
from ..models import AuditEntry

FIELDS = (
    "id",
    "ts",
    "organization_id",
    "organization_slug",
    "actor",
    "token",
    "address",
    "door",
    "action",
    "object",
    "status",
    "outcome",
    "data",
    "prev_hash",
    "hash",
)


class AuditEntrySerializer(serializers.ModelSerializer):
    """One entry of the trail, its hashes included so a reader can check the chain."""

    class Meta:
        model = AuditEntry
        fields = FIELDS
        read_only_fields = FIELDS


class AuditQuerySerializer(serializers.Serializer):
    """Filters, page and format of `GET /api/audit`; a bad value is a 400 naming its parameter."""

    since = serializers.DateTimeField(required=False, help_text="Entries at or after this time (ISO 8601).")
    until = serializers.DateTimeField(required=False, help_text="Entries before this time (ISO 8601).")
    actor = serializers.CharField(required=False, max_length=160, help_text="A username, or robot:<id>.")
    action = serializers.CharField(
        required=False, max_length=80, help_text="An action (robot.delete), or a prefix ending in * (robot.*)."
    )
    door = serializers.ChoiceField(choices=Door.choices, required=False)
    outcome = serializers.ChoiceField(choices=Outcome.choices, required=False)
    robot = serializers.SlugField(required=False, max_length=100, help_text="Entries on this robot and its parts.")
    object = serializers.CharField(required=False, max_length=300, help_text="Entries whose object starts so.")
    organization = serializers.SlugField(required=False, max_length=64, help_text="An organization's slug.")
    limit = serializers.IntegerField(required=False, min_value=1, max_value=1000, default=100)
    before = serializers.IntegerField(required=False, min_value=1, help_text="The page after this entry id (`next`).")
    format = serializers.ChoiceField(
        choices=[("json", "json"), ("csv", "csv")],
        required=False,
        default="json",
        help_text="json: a page; csv: every matching entry, streamed with a header row.",
    )
    download = serializers.BooleanField(
        required=False, default=False, help_text="With format=json: every matching entry as one streamed array."
    )

    def filtered(self, entries: QuerySet[AuditEntry]) -> QuerySet[AuditEntry]:
        """Apply the validated filters (not the page) to entries."""
        query: dict[str, Any] = self.validated_data
        if "since" in query:
            entries = entries.filter(ts__gte=query["since"])
        if "until" in query:
            entries = entries.filter(ts__lt=query["until"])
        if "actor" in query:
            entries = entries.filter(actor=query["actor"])
        if "action" in query:
            action = query["action"]
            entries = (
                entries.filter(action__startswith=action[:-1])
                if action.endswith("*")
                else entries.filter(action=action)
            )
        for name in ("door", "outcome"):
            if name in query:
                entries = entries.filter(**{name: query[name]})
        if "robot" in query:
            robot = f"robot/{query['robot']}"
            entries = entries.filter(Q(object=robot) | Q(object__startswith=f"{robot}/"))
        if "object" in query:
            entries = entries.filter(object__startswith=query["object"])
        if "organization" in query:
            entries = entries.filter(organization_slug=query["organization"])
        return entries
