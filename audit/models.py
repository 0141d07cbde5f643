"""The audit trail: append-only entries, each hashed together with the one before it."""

from __future__ import annotations

import hashlib
import json
from datetime import UTC
from typing import Any

from django.db import models
from django.utils import timezone

from .choices import Door, Outcome

GENESIS = "0" * 64
# The fields a hash covers, in a fixed order; the id is not among them (it is assigned by a sequence).
CHAINED = (
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
)


class AuditEntry(models.Model):
    """One state-changing action: who, from where, what, on which object, how it ended and when."""

    ts = models.DateTimeField(default=timezone.now)
    # Plain values, not a foreign key: deleting an organization must never rewrite its history.
    organization_id = models.BigIntegerField(null=True, blank=True)
    organization_slug = models.CharField(max_length=64, blank=True)
    actor = models.CharField(max_length=160, blank=True)  # a username, "robot:<id>", or "" when unknown
    token = models.CharField(max_length=100, blank=True)  # the API token's name when one was used
    address = models.CharField(max_length=64, blank=True)
    door = models.CharField(max_length=16, choices=Door.choices)
    action = models.CharField(max_length=80)
    object = models.CharField(max_length=300, blank=True)
    status = models.PositiveSmallIntegerField(default=200)
    outcome = models.CharField(max_length=16, choices=Outcome.choices, default=Outcome.OK)
    data = models.JSONField(default=dict, blank=True)
    prev_hash = models.CharField(max_length=64)
    hash = models.CharField(max_length=64, unique=True)

    class Meta:
        ordering = ["-id"]
        verbose_name_plural = "audit entries"
        indexes = [
            models.Index(fields=["organization_id", "-id"], name="audit_organization_id"),
            models.Index(fields=["ts"], name="audit_ts"),
        ]

    def __str__(self) -> str:
        return f"{self.ts:%Y-%m-%d %H:%M:%S} {self.actor or '-'} {self.action} {self.object} {self.outcome}"

    def chained(self) -> dict[str, Any]:
        """Return the fields the hash covers, as plain JSON values."""
        values = {name: getattr(self, name) for name in CHAINED}
        values["ts"] = self.ts.astimezone(UTC).isoformat()
        return values

    def digest(self) -> str:
        """Compute this entry's hash from its fields and the hash before it."""
        return chain_hash(self.prev_hash, self.chained())


def chain_hash(prev_hash: str, values: dict[str, Any]) -> str:
    """Hash an entry's fields together with the previous entry's hash."""
    body = json.dumps(values, sort_keys=True, separators=(",", ":"), ensure_ascii=False)
    return hashlib.sha256(f"{prev_hash}\n{body}".encode()).hexdigest()


class AuditAnchor(models.Model):
    """Where retention cut the chain: the first kept entry and the hash it chains to."""

    first_id = models.BigIntegerField(unique=True)
    prev_hash = models.CharField(max_length=64)
    removed = models.PositiveIntegerField()
    created_at = models.DateTimeField(default=timezone.now)

    class Meta:
        ordering = ["-first_id"]

    def __str__(self) -> str:
        return f"entries before {self.first_id} removed ({self.removed})"
