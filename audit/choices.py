"""The doors an audited action comes through, and the words of its outcome."""

from __future__ import annotations

from django.db import models


class Door(models.TextChoices):
    """Where an action came in."""

    REST = "rest", "Robot API"
    ADMIN = "admin", "Django admin"
    DASHBOARD = "dashboard", "Dashboard"
    WS = "ws", "Client WebSocket"
    BRIDGE = "bridge", "Bridge"
    REGISTRY = "registry", "Registry"
    LOGIN = "login", "Login"
    SYSTEM = "system", "The cloud itself"


class Outcome(models.TextChoices):
    """How an action ended, in one word (the status says more)."""

    OK = "ok", "Done"
    DENIED = "denied", "Denied"
    NOT_FOUND = "not_found", "Not found"
    INVALID = "invalid", "Invalid"
    FAILED = "failed", "Failed"


def outcome_of(status: int) -> Outcome:
    """Name the outcome of an HTTP-like status."""
    if status < 400:
        return Outcome.OK
    if status in (401, 403, 429):
        return Outcome.DENIED
    if status == 404:
        return Outcome.NOT_FOUND
    if status < 500:
        return Outcome.INVALID
    return Outcome.FAILED
