"""Serializers of the Robot API about recordings."""

from __future__ import annotations

from rest_framework import serializers

from bridgeos_agent.protocol import (
    MAX_RECORDING_BYTES,
    MAX_RECORDING_DURATION_S,
    MAX_RECORDING_TOPICS,
    MIN_RECORDING_BYTES,
)

from ..choices import RosProfile
from ..models import Recording
from ..services import DEFAULT_MAX_BYTES, DEFAULT_MAX_DURATION_S

TOPIC_PATTERN = r"^/[A-Za-z0-9_/]{1,255}$"


class RecordingStartSerializer(serializers.Serializer):
    """What to record and the limits that end the recording."""

    topics = serializers.ListField(
        child=serializers.RegexField(
            TOPIC_PATTERN, error_messages={"invalid": "An absolute ROS topic name, e.g. /chatter."}
        ),
        min_length=1,
        max_length=MAX_RECORDING_TOPICS,
    )
    ros = serializers.ChoiceField(
        RosProfile.choices, required=False, help_text="ros1 or ros2; by default the graph that has every topic."
    )
    max_bytes = serializers.IntegerField(
        min_value=MIN_RECORDING_BYTES,
        max_value=MAX_RECORDING_BYTES,
        default=DEFAULT_MAX_BYTES,
        help_text="Message bytes recorded at most; reaching it ends the recording.",
    )
    max_duration_s = serializers.FloatField(
        min_value=0.1,
        max_value=MAX_RECORDING_DURATION_S,
        default=DEFAULT_MAX_DURATION_S,
        help_text="Seconds recorded at most; reaching it ends the recording.",
    )

    def validate_topics(self, topics: list[str]) -> list[str]:
        if len(set(topics)) != len(topics):
            raise serializers.ValidationError("Name each topic once.")
        return topics


class RecordingSerializer(serializers.ModelSerializer):
    """A recording as the API shows it, with where to download it."""

    id = serializers.CharField(source="id.hex")
    robot = serializers.CharField(source="robot_id")
    download = serializers.SerializerMethodField()

    class Meta:
        model = Recording
        fields = [
            "id",
            "robot",
            "topics",
            "ros",
            "status",
            "message",
            "max_bytes",
            "max_duration_s",
            "created_at",
            "started_at",
            "stopped_at",
            "duration_s",
            "message_count",
            "data_bytes",
            "size_bytes",
            "download",
        ]

    def get_download(self, recording: Recording) -> str | None:
        if not recording.file:
            return None
        path = f"/api/robot/{recording.robot_id}/recordings/{recording.id.hex}/download"
        request = self.context.get("request")
        return request.build_absolute_uri(path) if request is not None else path
