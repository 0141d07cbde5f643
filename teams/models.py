"""Organizations, which own robots and everything on them, and their members with a role each."""

from __future__ import annotations

from django.conf import settings
from django.core.validators import RegexValidator
from django.db import models
from django.utils import timezone

from .naming import SLUG_PATTERN
from .roles import Role

slug_validator = RegexValidator(
    SLUG_PATTERN, "Use lowercase letters and digits, separated by single '.', '_' or '-' (it names registry images)."
)


class Organization(models.Model):
    """A team that owns robots, Skills, templates, recordings, registry images and events."""

    slug = models.CharField(max_length=64, unique=True, validators=[slug_validator])
    name = models.CharField(max_length=200, blank=True)
    # The user whose own organization this is (made for every user); None for a team's.
    personal_of = models.OneToOneField(
        settings.AUTH_USER_MODEL,
        on_delete=models.CASCADE,
        null=True,
        blank=True,
        related_name="personal_organization",
    )
    created_at = models.DateTimeField(default=timezone.now, editable=False)

    class Meta:
        ordering = ["slug"]

    def __str__(self) -> str:
        return self.name or self.slug


class Membership(models.Model):
    """A user's role in an organization."""

    organization = models.ForeignKey(Organization, on_delete=models.CASCADE, related_name="memberships")
    user = models.ForeignKey(settings.AUTH_USER_MODEL, on_delete=models.CASCADE, related_name="memberships")
    role = models.CharField(max_length=16, choices=Role.choices)
    created_at = models.DateTimeField(default=timezone.now, editable=False)

    class Meta:
        ordering = ["organization", "user"]
        constraints = [models.UniqueConstraint(fields=["organization", "user"], name="one_membership_per_user")]
        indexes = [models.Index(fields=["user", "organization"], name="membership_user_organization")]

    def __str__(self) -> str:
        return f"{self.user} is {self.role} of {self.organization}"
