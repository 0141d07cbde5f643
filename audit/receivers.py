"""Write logins, failed logins and logouts at every door from Django's auth signals, once each."""

from __future__ import annotations

from typing import Any

from django.contrib.auth.signals import user_logged_in, user_logged_out, user_login_failed
from django.dispatch import receiver

from . import services
from .choices import Door, Outcome
from .middleware import door_of, mark_audited


def _where(request: Any) -> tuple[str, str]:
    """Return the door and address of a login request (none: a login from code)."""
    if request is None:
        return Door.SYSTEM, ""
    path = getattr(request, "path", "")
    door = Door.LOGIN if path.startswith("/accounts/") else door_of(path)
    return door, request.META.get("REMOTE_ADDR", "")


@receiver(user_logged_in, dispatch_uid="audit.login")
def audit_login(sender: Any, request: Any, user: Any, **kwargs: Any) -> None:
    """Write a session login."""
    door, address = _where(request)
    services.record_quietly("login", door=door, actor=user.get_username(), address=address)
    if request is not None:
        mark_audited(request)


@receiver(user_login_failed, dispatch_uid="audit.login_failed")
def audit_login_failed(sender: Any, credentials: dict[str, Any], request: Any = None, **kwargs: Any) -> None:
    """Write a failed login (a session's or HTTP Basic's), naming the username it tried."""
    door, address = _where(request)
    services.record_quietly(
        "login.failed",
        door=door,
        actor=str(credentials.get("username", "")),
        address=address,
        status=401,
        outcome=Outcome.DENIED,
    )
    if request is not None:
        mark_audited(request)


@receiver(user_logged_out, dispatch_uid="audit.logout")
def audit_logout(sender: Any, request: Any, user: Any, **kwargs: Any) -> None:
    """Write a logout."""
    if user is None:
        return
    door, address = _where(request)
    services.record_quietly("logout", door=door, actor=user.get_username(), address=address)
