"""Shapes of the Robot API's requests and answers about releases."""

from __future__ import annotations

from typing import Any

from django.db.models import F
from drf_spectacular.utils import extend_schema_field
from rest_framework import serializers

from bridgeos_agent.skillconfig import SLUG_PATTERN
from teams.naming import MAX_SLUG

from ..models import Release, Rollout, RolloutRobot, UpdateHold


class ReleaseSerializer(serializers.ModelSerializer):
    organization = serializers.CharField(source="organization.slug", read_only=True)
    created_by = serializers.CharField(source="created_by_name", read_only=True)

    class Meta:
        model = Release
        fields = ["id", "organization", "skill_id", "number", "name", "notes", "config", "created_by", "created_at"]
        read_only_fields = fields


class ReleaseCreateSerializer(serializers.Serializer):
    organization = serializers.CharField(
        required=False,
        max_length=MAX_SLUG,
        help_text="Slug of the organization it belongs to (you must be a developer there); "
        "default: your token's or session's organization, or your only one.",
    )
    config = serializers.JSONField(help_text="A Skill config (thesis Table 4.1); its skill_id names the Skill.")
    name = serializers.CharField(required=False, allow_blank=True, max_length=200, default="")
    notes = serializers.CharField(required=False, allow_blank=True, max_length=10000, default="")


class ReleaseQuerySerializer(serializers.Serializer):
    organization = serializers.CharField(required=False, max_length=MAX_SLUG, help_text="An organization's slug.")
    skill = serializers.RegexField(SLUG_PATTERN, required=False, max_length=64, help_text="A Skill's skill_id.")


class RolloutCreateSerializer(serializers.Serializer):
    release = serializers.IntegerField(min_value=1, help_text="The id of the release to roll out.")
    selector = serializers.CharField(
        max_length=1000, help_text="The group: labels the robots match, e.g. site=lab,model=turtlebot,!retired."
    )
    follow = serializers.BooleanField(
        default=False, help_text="Robots that join the group later (labelled or created so) get the release too."
    )
    strategy = serializers.JSONField(
        required=False,
        default=None,
        help_text="first (3 or '10%'), growth (exponential|fixed), factor, pause_s (null: wait for resume), "
        "max_unavailable, soak_s, failure_threshold_pct, min_robots, on_failure (rollback|pause).",
    )
    gates = serializers.JSONField(
        required=False, default=None, help_text='{"conditions": ["cpu < 0.8", "metric:detections_per_s > 5"]}'
    )


class RolloutRobotSerializer(serializers.ModelSerializer):
    robot = serializers.CharField(source="robot_id", read_only=True)

    class Meta:
        model = RolloutRobot
        fields = [
            "robot",
            "batch",
            "status",
            "reason",
            "touched",
            "bytes_done",
            "bytes_total",
            "started_at",
            "verify_from",
            "finished_at",
        ]
        read_only_fields = fields


class RolloutSerializer(serializers.ModelSerializer):
    organization = serializers.CharField(source="organization.slug", read_only=True)
    release = serializers.IntegerField(source="release_id", read_only=True)
    skill_id = serializers.CharField(source="release.skill_id", read_only=True)
    release_number = serializers.IntegerField(source="release.number", read_only=True)
    created_by = serializers.CharField(source="created_by_name", read_only=True)

    class Meta:
        model = Rollout
        fields = [
            "id",
            "organization",
            "release",
            "skill_id",
            "release_number",
            "selector",
            "follow",
            "strategy",
            "gates",
            "state",
            "reason",
            "batch",
            "batch_sizes",
            "batch_started_at",
            "next_batch_at",
            "created_by",
            "created_at",
            "updated_at",
            "finished_at",
        ]
        read_only_fields = fields


ROBOT_FIELDS = RolloutRobotSerializer.Meta.fields


class RolloutDetailSerializer(RolloutSerializer):
    counts = serializers.SerializerMethodField()
    batches = serializers.SerializerMethodField()
    robots = serializers.SerializerMethodField()

    class Meta(RolloutSerializer.Meta):
        fields = [*RolloutSerializer.Meta.fields, "counts", "batches", "robots"]
        read_only_fields = fields

    def _rows(self, rollout: Rollout) -> list[dict[str, Any]]:
        """Its robots as plain rows, read once: a page polls this every second for a thousand robots."""
        cached = getattr(rollout, "_detail_rows", None)
        if cached is None:
            rows = rollout.robots.order_by("batch", "robot_id").values(*ROBOT_FIELDS[1:], robot_key=F("robot_id"))
            cached = [{"robot": row.pop("robot_key"), **row} for row in rows]
            rollout._detail_rows = cached  # type: ignore[attr-defined]
        return cached

    def get_counts(self, rollout: Rollout) -> dict[str, int]:
        found = dict.fromkeys(RolloutRobot.Status.values, 0)
        for row in self._rows(rollout):
            found[row["status"]] += 1
        return found

    def get_batches(self, rollout: Rollout) -> list[dict[str, Any]]:
        """Each batch's size, where it stands (done, running, waiting) and its robots' statuses counted."""
        batches = [
            {"index": index, "size": size, "state": _batch_state(rollout, index), "counts": {}}
            for index, size in enumerate(rollout.batch_sizes)
        ]
        for row in self._rows(rollout):
            if row["batch"] < len(batches):
                counted = batches[row["batch"]]["counts"]
                counted[row["status"]] = counted.get(row["status"], 0) + 1
        return batches

    @extend_schema_field(RolloutRobotSerializer(many=True))
    def get_robots(self, rollout: Rollout) -> list[dict[str, Any]]:
        return [
            {**row, **{key: row[key].isoformat().replace("+00:00", "Z") for key in DATES if row[key] is not None}}
            for row in self._rows(rollout)
        ]


DATES = ("started_at", "verify_from", "finished_at")


def _batch_state(rollout: Rollout, index: int) -> str:
    if index < rollout.batch:
        return "done"
    if index > rollout.batch:
        return "waiting"
    return "running" if rollout.active else rollout.state


class HoldSerializer(serializers.ModelSerializer):
    robot = serializers.CharField(source="robot_id", read_only=True)

    class Meta:
        model = UpdateHold
        fields = ["robot", "holder", "reason", "until", "created_at"]
        read_only_fields = fields


class HoldCreateSerializer(serializers.Serializer):
    seconds = serializers.FloatField(help_text="How long at most: the hold's deadline, after which updates install.")
    reason = serializers.CharField(required=False, allow_blank=True, max_length=500, default="")
