"""Robots attached to the cloud, with their configuration and hashed token."""

from __future__ import annotations

import hashlib
import hmac
import secrets
from datetime import datetime
from typing import Any

from django.conf import settings
from django.core.validators import RegexValidator
from django.db import models
from django.utils import timezone

from bridgeos_agent.robotconfig import RobotConfig, parse_robot_config
from bridgeos_agent.skillconfig import SLUG_PATTERN
from bridgeos_cloud.validation import validated_config

from .choices import RobotStatus
from .labels import validate_labels
from .signals import config_checked

id_validator = RegexValidator(
    SLUG_PATTERN, "Use 1-64 lowercase letters, digits, '-' or '_', starting with a letter or digit."
)
TOKEN_PREFIX = "brt_"


def default_robot_config() -> dict[str, Any]:
    """Return the config a new robot starts with."""
    return RobotConfig().model_dump(mode="json")


def hash_token(token: str) -> str:
    """Hash a robot token; tokens are 256-bit random, so a plain SHA-256 is enough."""
    return hashlib.sha256(token.encode()).hexdigest()


class Robot(models.Model):
    """A robot whose Robot Controller connects to this cloud."""

    id = models.CharField(primary_key=True, max_length=64, validators=[id_validator])
    name = models.CharField(max_length=200, blank=True)
    organization = models.ForeignKey("teams.Organization", on_delete=models.CASCADE, related_name="robots")
    # Who added the robot; the robot belongs to its organization and outlives them.
    owner = models.ForeignKey(
        settings.AUTH_USER_MODEL, on_delete=models.SET_NULL, null=True, blank=True, related_name="robots"
    )
    status = models.CharField(max_length=16, choices=RobotStatus.choices, default=RobotStatus.IDLE)
    connected = models.BooleanField(default=False)
    last_seen = models.DateTimeField(null=True, blank=True)
    # The consumer holding the live connection; commands go there, and only it may mark the robot offline.
    channel = models.CharField(max_length=200, blank=True, editable=False)
    # The ROS master the robot's components use: the one it reported, or one the cloud runs.
    ros_master = models.CharField(max_length=2048, blank=True, editable=False)
    # The robot's ROS 2 graph as its agent reported it at login (protocol.Ros2GraphInfo), with the
    # "cloud_discovery_server" its cloud copies use ("host:port"); None: no ROS 2 there.
    ros2 = models.JSONField(null=True, blank=True, editable=False)
    # Operator's key=value tags (robots.labels rules); selectors name groups of robots by them.
    labels = models.JSONField(default=dict, blank=True, help_text='key: value labels, e.g. {"site": "lab"}.')
    config = models.JSONField(
        default=default_robot_config, help_text="Resources, heuristic, threshold, offloading mode, subnets."
    )
    token_hash = models.CharField(max_length=64, editable=False)
    # The token a rotation replaced, still good until ``previous_token_until`` so a fleet re-keys without a drop.
    previous_token_hash = models.CharField(max_length=64, blank=True, editable=False)
    previous_token_until = models.DateTimeField(null=True, blank=True, editable=False)
    created_at = models.DateTimeField(default=timezone.now, editable=False)

    class Meta:
        ordering = ["id"]
        indexes = [models.Index(fields=["organization", "id"], name="robot_organization_id")]
        # A GIN index on labels (serving a selector's `@>`) is added on PostgreSQL by migration 0009.

    def __str__(self) -> str:
        return self.name or self.id

    def save(self, *args: Any, **kwargs: Any) -> None:
        # Configs are validated on every save, not only in forms, so no door can store a bad one.
        self.clean()
        super().save(*args, **kwargs)

    def clean(self) -> None:
        # An emptied admin field arrives as None: it means no labels.
        self.labels = validate_labels({} if self.labels is None else self.labels)
        self.config = validated_config(parse_robot_config, self.config)
        # The apps above this one (the network's subnets) check their parts of the config.
        config_checked.send(sender=Robot, robot_id=self.id, config=self.config)

    def issue_token(self, *, grace_until: datetime | None = None) -> str:
        """Replace the robot's token and return the new one; the old one stays good until ``grace_until``."""
        token = TOKEN_PREFIX + secrets.token_urlsafe(32)
        if grace_until is not None and self.token_hash:
            self.previous_token_hash, self.previous_token_until = self.token_hash, grace_until
        else:
            self.previous_token_hash, self.previous_token_until = "", None
        self.token_hash = hash_token(token)
        return token

    def check_token(self, token: str) -> bool:
        """Tell whether a presented token is this robot's, or its previous one within its grace, in constant time."""
        return token_matches(self.token_hash, self.previous_token_hash, self.previous_token_until, token)


def token_matches(current: str, previous: str, previous_until: datetime | None, token: str) -> bool:
    """Tell whether a token hashes to a robot's current hash, or its previous one before its grace ends."""
    presented = hash_token(token)
    ok = bool(current) and hmac.compare_digest(current, presented)
    if previous and previous_until is not None and previous_until > timezone.now():
        ok = hmac.compare_digest(previous, presented) or ok
    return ok


class ApiToken(models.Model):
    """A user's API token: stored hashed, valid until it expires.

    A token made from a login (/api/auth) acts with the user's own roles in each of their
    organizations; a scoped token names one organization and a role at most the user's there.
    """

    user = models.ForeignKey(settings.AUTH_USER_MODEL, on_delete=models.CASCADE, related_name="api_tokens")
    name = models.CharField(max_length=100, blank=True)
    organization = models.ForeignKey(
        "teams.Organization", on_delete=models.CASCADE, null=True, blank=True, related_name="api_tokens"
    )
    role = models.CharField(max_length=16, blank=True)
    key_hash = models.CharField(max_length=64, unique=True, editable=False)
    created_at = models.DateTimeField(default=timezone.now, editable=False)
    expires_at = models.DateTimeField(null=True, blank=True, help_text="None: until revoked.")

    class Meta:
        indexes = [models.Index(fields=["expires_at"])]

    def __str__(self) -> str:
        until = "revoked" if self.expires_at is None else f"{self.expires_at:%Y-%m-%d %H:%M}"
        return f"token {self.name or self.pk} of {self.user} until {until}"

    @property
    def expired(self) -> bool:
        return self.expires_at is not None and self.expires_at <= timezone.now()


class BridgeTicket(models.Model):
    """A browser's single-use pass to one robot's bridge WebSockets: stored hashed, short-lived."""

    key_hash = models.CharField(max_length=64, unique=True, editable=False)
    user = models.ForeignKey(settings.AUTH_USER_MODEL, on_delete=models.CASCADE, related_name="bridge_tickets")
    robot = models.ForeignKey(Robot, on_delete=models.CASCADE, related_name="bridge_tickets")
    expires_at = models.DateTimeField()

    class Meta:
        indexes = [models.Index(fields=["expires_at"])]

    def __str__(self) -> str:
        return f"bridge ticket of {self.user} for {self.robot_id} until {self.expires_at:%H:%M:%S}"
