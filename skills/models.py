"""Skills deployed on robots, their components, and the catalog of Skill templates."""

from __future__ import annotations

from typing import Any

from django.core.exceptions import ValidationError
from django.db import models
from django.utils import timezone

from bridgeos_agent.protocol import ComponentStatusName, SkillStatusName
from bridgeos_agent.skillconfig import parse_skill_config
from bridgeos_cloud.validation import validated_config
from robots.models import Robot, id_validator

from .choices import ACTIVE_LOCATION_CHOICES, COMPONENT_STATUS_CHOICES, LOCATION_CHOICES, SKILL_STATUS_CHOICES


class Skill(models.Model):
    """A Skill added to one robot, configured by a Skill config (thesis Table 4.1)."""

    robot = models.ForeignKey(Robot, on_delete=models.CASCADE, related_name="skills")
    skill_id = models.CharField(max_length=64, validators=[id_validator])
    name = models.CharField(max_length=200)
    config = models.JSONField()
    status = models.CharField(max_length=16, choices=SKILL_STATUS_CHOICES, default=SkillStatusName.STOPPED.value)
    created_at = models.DateTimeField(default=timezone.now, editable=False)
    updated_at = models.DateTimeField(auto_now=True)

    class Meta:
        ordering = ["robot_id", "skill_id"]
        constraints = [models.UniqueConstraint(fields=["robot", "skill_id"], name="unique_skill_per_robot")]

    def __str__(self) -> str:
        return f"{self.robot_id}/{self.skill_id}"

    def save(self, *args: Any, **kwargs: Any) -> None:
        self.clean()
        super().save(*args, **kwargs)

    def clean(self) -> None:
        self.config = validated_config(parse_skill_config, self.config)


class Component(models.Model):
    """One containerised component of a Skill, and where it runs now."""

    skill = models.ForeignKey(Skill, on_delete=models.CASCADE, related_name="components")
    component_id = models.CharField(max_length=64, validators=[id_validator])
    location = models.CharField(max_length=8, choices=LOCATION_CHOICES, help_text="Where the config allows it to run.")
    active_location = models.CharField(max_length=8, choices=ACTIVE_LOCATION_CHOICES, blank=True)
    status = models.CharField(
        max_length=16, choices=COMPONENT_STATUS_CHOICES, default=ComponentStatusName.STOPPED.value
    )
    message = models.TextField(
        blank=True, default="", help_text="Why the component is in its status, as the robot said (why it failed)."
    )
    container = models.JSONField(default=dict, blank=True, help_text="Container id, address, image, ports.")
    resources = models.JSONField(default=dict, blank=True, help_text="cpu, gpu, ram, bandwidth, io.")
    updated_at = models.DateTimeField(auto_now=True)

    class Meta:
        ordering = ["skill_id", "component_id"]
        constraints = [
            models.UniqueConstraint(fields=["skill", "component_id"], name="unique_component_per_skill"),
            models.CheckConstraint(condition=~models.Q(active_location="either"), name="active_location_is_a_side"),
        ]

    def __str__(self) -> str:
        return f"{self.skill}/{self.component_id}"


class SkillTemplate(models.Model):
    """A Skill config in the catalog, ready to be added to any robot."""

    # None: the cloud's own catalog, which every organization reads and staff keep.
    organization = models.ForeignKey(
        "teams.Organization", on_delete=models.CASCADE, null=True, blank=True, related_name="templates"
    )
    name = models.CharField(max_length=200)
    description = models.TextField(blank=True)
    config = models.JSONField()
    tags = models.JSONField(default=list, blank=True)
    created_at = models.DateTimeField(default=timezone.now, editable=False)

    class Meta:
        ordering = ["name"]
        constraints = [
            models.UniqueConstraint(fields=["organization", "name"], name="template_name_per_organization"),
            models.UniqueConstraint(
                fields=["name"], condition=models.Q(organization=None), name="template_name_in_catalog"
            ),
        ]

    def __str__(self) -> str:
        return self.name

    def save(self, *args: Any, **kwargs: Any) -> None:
        self.clean()
        super().save(*args, **kwargs)

    def clean(self) -> None:
        self.config = validated_config(parse_skill_config, self.config)
        self.tags = _validated_tags(self.tags)


def _validated_tags(tags: Any) -> list[str]:
    """Return tags as a list of short strings, or raise a field error."""
    if not isinstance(tags, list) or not all(isinstance(tag, str) and 0 < len(tag) <= 50 for tag in tags):
        raise ValidationError({"tags": ["Tags must be a list of strings of 1-50 characters."]})
    return tags


class CloudInstance(models.Model):
    """The cloud copy of a component: whether it should run, what runs, and where robots reach it."""

    class Desired(models.TextChoices):
        RUNNING = "running", "Running"
        STOPPED = "stopped", "Stopped"

    component = models.OneToOneField(Component, on_delete=models.CASCADE, related_name="cloud")
    desired = models.CharField(max_length=8, choices=Desired.choices, default=Desired.STOPPED)
    # A fresh token per start or stop request: a task carrying an older one has been superseded.
    token = models.CharField(max_length=32, blank=True)
    status = models.CharField(
        max_length=16, choices=COMPONENT_STATUS_CHOICES, default=ComponentStatusName.STOPPED.value
    )
    runtime = models.CharField(max_length=16, blank=True)
    # What robots are told: {"runtime", "id", "address", "ports": {"<container port>": <published port>}}.
    container = models.JSONField(default=dict, blank=True)
    message = models.TextField(blank=True, help_text="Why the last start failed or the copy crashed.")
    restarts = models.PositiveIntegerField(default=0, help_text="Crash restarts since the last start request.")
    crashes = models.JSONField(default=list, blank=True, help_text="Unix times of recent crashes.")
    restart_at = models.DateTimeField(null=True, blank=True, help_text="When a crashed copy is started again.")
    updated_at = models.DateTimeField(auto_now=True)

    class Meta:
        indexes = [models.Index(fields=["desired", "status"])]

    def __str__(self) -> str:
        return f"cloud copy of {self.component_id}: {self.status} (wants {self.desired})"


class RobotCloud(models.Model):
    """What the cloud runs for one robot besides its components: its network, ROS master and ROS 2 discovery server."""

    robot = models.OneToOneField(Robot, on_delete=models.CASCADE, primary_key=True, related_name="cloud")
    network = models.CharField(max_length=128, blank=True, help_text="The robot's cloud network, once created.")
    ros_master_port = models.PositiveIntegerField(null=True, blank=True, unique=True)
    ros_master_status = models.CharField(
        max_length=16, choices=COMPONENT_STATUS_CHOICES, default=ComponentStatusName.STOPPED.value
    )
    # The Fast DDS discovery server of the robot's ROS 2 cloud graph (a UDP port of the cloud host).
    ros2_discovery_port = models.PositiveIntegerField(null=True, blank=True, unique=True)
    ros2_discovery_status = models.CharField(
        max_length=16, choices=COMPONENT_STATUS_CHOICES, default=ComponentStatusName.STOPPED.value
    )
    message = models.TextField(blank=True)
    updated_at = models.DateTimeField(auto_now=True)

    def __str__(self) -> str:
        return f"cloud side of {self.robot_id}"


class CloudRelay(models.Model):
    """The cloud relay of one robot Skill (cloud-side routing): its control port and whether it runs.

    Its token is not kept: it is derived from SECRET_KEY and ``nonce`` (random per relay), so the
    database alone never yields it and every cloud process (login answer, worker) derives the same one.
    """

    skill = models.OneToOneField(Skill, on_delete=models.CASCADE, primary_key=True, related_name="cloud_relay")
    port = models.PositiveIntegerField(unique=True, help_text="The relay's control port on the cloud host.")
    nonce = models.CharField(max_length=64)
    status = models.CharField(
        max_length=16, choices=COMPONENT_STATUS_CHOICES, default=ComponentStatusName.STOPPED.value
    )
    message = models.TextField(blank=True)
    updated_at = models.DateTimeField(auto_now=True)

    def __str__(self) -> str:
        return f"cloud relay of {self.skill_id}: {self.status}"
