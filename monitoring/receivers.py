"""Log in the event log what lower layers announce by signal."""

from __future__ import annotations

from typing import Any

from django.dispatch import receiver

from bridgeos_cloud.bruteforce import login_blocked

from .choices import Level
from .services import record_event


@receiver(login_blocked, dispatch_uid="monitoring-login-blocked")
def log_login_blocked(sender: Any, scope: str, identity: str, address: str, **kw: Any) -> None:
    """Record that an identity is blocked after too many failed logins."""
    record_event(
        f"Too many failed authentications of {scope} {identity[:150]} from {address}",
        level=Level.WARNING,
        kind="authentication_blocked",
        data={scope: identity[:150], "address": address},
    )
