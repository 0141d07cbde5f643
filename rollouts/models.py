"""Releases: immutable, numbered versions of a Skill, every image pinned by digest."""

from __future__ import annotations

from typing import Any

from django.conf import settings
from django.db import models
from django.utils import timezone


class ImmutableError(Exception):
    """A release was asked to change: it is never edited, only superseded by a new one."""


class Release(models.Model):
    """One numbered version of an organization's Skill: its config, every image pinned, as it was made."""

    organization = models.ForeignKey("teams.Organization", on_delete=models.CASCADE, related_name="releases")
    skill_id = models.SlugField(max_length=64)
    # 1, 2, 3... per organization and Skill, in the order the releases were made.
    number = models.PositiveIntegerField()
    name = models.CharField(max_length=200, blank=True)
    notes = models.TextField(blank=True)
    config = models.JSONField()
    created_by = models.ForeignKey(
        settings.AUTH_USER_MODEL, on_delete=models.SET_NULL, null=True, blank=True, related_name="+"
    )
    # Who made it, kept when their account is deleted.
    created_by_name = models.CharField(max_length=150, blank=True)
    created_at = models.DateTimeField(default=timezone.now, editable=False)

    class Meta:
        ordering = ["organization", "skill_id", "-number"]
        constraints = [
            models.UniqueConstraint(fields=["organization", "skill_id", "number"], name="release_number_per_skill"),
        ]

    def __str__(self) -> str:
        return f"{self.skill_id} #{self.number}"

    def save(self, *args: Any, **kwargs: Any) -> None:
        if not self._state.adding:
            raise ImmutableError(f"Release {self} is immutable: make a new release instead.")
        super().save(*args, **kwargs)

    @property
    def robot_images(self) -> set[str]:
        """The images the release's robot copies run: what a robot fetches before it installs the release."""
        return {
            component["robot"]["image"]
            for component in self.config.get("components", {}).values()
            if component.get("location") != "cloud" and (component.get("robot") or {}).get("image")
        }


class Rollout(models.Model):
    """A release going out to a group of robots in batches, each gated on the robots' health."""

    class State(models.TextChoices):
        RUNNING = "running", "Running"
        PAUSED = "paused", "Paused"
        SUCCEEDED = "succeeded", "Succeeded"
        ROLLING_BACK = "rolling_back", "Rolling back"
        ROLLED_BACK = "rolled_back", "Rolled back"
        ABORTED = "aborted", "Aborted"

    organization = models.ForeignKey("teams.Organization", on_delete=models.CASCADE, related_name="rollouts")
    release = models.ForeignKey(Release, on_delete=models.PROTECT, related_name="rollouts")
    selector = models.CharField(max_length=1000, help_text="The group: robots whose labels match (site=lab,model=x).")
    follow = models.BooleanField(default=False, help_text="Robots that join the group later get the release too.")
    strategy = models.JSONField(default=dict, blank=True)
    gates = models.JSONField(default=dict, blank=True)
    state = models.CharField(max_length=16, choices=State.choices, default=State.RUNNING)
    # Why it is in its state: the failed gate, who paused it, what rolled it back.
    reason = models.TextField(blank=True)
    # The sizes of its batches, fixed when it was made (a followed robot joins the batch running then).
    batch_sizes = models.JSONField(default=list)
    batch = models.PositiveIntegerField(default=0, help_text="The batch running now, from 0.")
    batch_started_at = models.DateTimeField(null=True, blank=True)
    # When the next batch may start (a pause between batches); None: at once, or at an operator's resume.
    next_batch_at = models.DateTimeField(null=True, blank=True)
    created_by = models.ForeignKey(
        settings.AUTH_USER_MODEL, on_delete=models.SET_NULL, null=True, blank=True, related_name="+"
    )
    created_by_name = models.CharField(max_length=150, blank=True)
    created_at = models.DateTimeField(default=timezone.now, editable=False)
    updated_at = models.DateTimeField(auto_now=True)
    finished_at = models.DateTimeField(null=True, blank=True)

    class Meta:
        ordering = ["-created_at", "-id"]
        indexes = [models.Index(fields=["state"])]

    def __str__(self) -> str:
        return f"rollout {self.pk} of {self.release}: {self.state}"

    @property
    def active(self) -> bool:
        return self.state in (self.State.RUNNING, self.State.PAUSED, self.State.ROLLING_BACK)


class RolloutRobot(models.Model):
    """One robot of a rollout: its batch, where it stands, and the version it ran before (for a rollback)."""

    class Status(models.TextChoices):
        PENDING = "pending", "Pending"
        DOWNLOADING = "downloading", "Downloading"
        DEFERRED = "deferred", "Deferred"
        INSTALLING = "installing", "Installing"
        VERIFYING = "verifying", "Verifying"
        SUCCEEDED = "succeeded", "Succeeded"
        FAILED = "failed", "Failed"
        ROLLING_BACK = "rolling_back", "Rolling back"
        ROLLED_BACK = "rolled_back", "Rolled back"
        OFFLINE = "offline", "Offline"

    rollout = models.ForeignKey(Rollout, on_delete=models.CASCADE, related_name="robots")
    robot = models.ForeignKey("robots.Robot", on_delete=models.CASCADE, related_name="rollouts")
    batch = models.PositiveIntegerField()
    status = models.CharField(max_length=16, choices=Status.choices, default=Status.PENDING)
    # The executor's step within a status ("stopping" the old version, "starting" the new one).
    step = models.CharField(max_length=16, blank=True)
    reason = models.TextField(blank=True)
    # Whether the rollout changed the robot: only a touched robot is rolled back.
    touched = models.BooleanField(default=False)
    # The Skill config the robot had before (None: it had no such Skill) and whether that ran.
    previous_config = models.JSONField(null=True, blank=True)
    previous_running = models.BooleanField(default=False)
    bytes_done = models.BigIntegerField(default=0)
    bytes_total = models.BigIntegerField(default=0)
    started_at = models.DateTimeField(null=True, blank=True)
    verify_from = models.DateTimeField(null=True, blank=True)
    finished_at = models.DateTimeField(null=True, blank=True)
    updated_at = models.DateTimeField(auto_now=True)

    class Meta:
        ordering = ["rollout_id", "batch", "robot_id"]
        constraints = [models.UniqueConstraint(fields=["rollout", "robot"], name="robot_once_per_rollout")]
        indexes = [models.Index(fields=["robot", "status"])]

    def __str__(self) -> str:
        return f"{self.robot_id} in rollout {self.rollout_id}: {self.status}"


class UpdateHold(models.Model):
    """A robot asking not to be updated now (busy): a rollout defers it until released or past its deadline."""

    robot = models.OneToOneField("robots.Robot", on_delete=models.CASCADE, primary_key=True, related_name="hold")
    # Who holds it: "owner" (through the Robot API) or a component's name (through the Components API).
    holder = models.CharField(max_length=200)
    reason = models.CharField(max_length=500, blank=True)
    until = models.DateTimeField(help_text="The deadline: past it, the hold no longer defers an update.")
    created_at = models.DateTimeField(default=timezone.now)

    def __str__(self) -> str:
        return f"hold on {self.robot_id} by {self.holder} until {self.until:%Y-%m-%d %H:%M:%S}"

    def active(self, now: Any = None) -> bool:
        return self.until > (now or timezone.now())
