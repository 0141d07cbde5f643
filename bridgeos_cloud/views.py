"""Site-wide views: the health check, and the brute-force limit on the login forms."""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Callable

from django.conf import settings
from django.db import connection
from django.http import HttpRequest, HttpResponse
from drf_spectacular.utils import OpenApiResponse, extend_schema
from rest_framework.decorators import api_view, permission_classes
from rest_framework.permissions import AllowAny
from rest_framework.request import Request
from rest_framework.response import Response

from bridgeos_agent.logonce import LogOnce

from . import bruteforce

logger = logging.getLogger(__name__)


@extend_schema(
    responses={200: OpenApiResponse(description="All parts answer"), 503: OpenApiResponse(description="A part is down")}
)
@api_view(["GET"])
@permission_classes([AllowAny])
def health(request: Request) -> Response:
    """Report whether the database and the channel layer backend answer."""
    checks = {"database": _database_ok(), "redis": _redis_ok() if settings.REDIS_URL else "not configured"}
    healthy = all(value is True or value == "not configured" for value in checks.values())
    return Response({"status": "ok" if healthy else "degraded", **checks}, status=200 if healthy else 503)


def _database_ok() -> bool:
    try:
        with connection.cursor() as cursor:
            cursor.execute("SELECT 1")
    except Exception as exc:
        # Reported as "degraded" to whoever asks; the log says why, once per distinct error.
        _database_failures.failed(exc)
        return False
    _database_failures.worked()
    return True


_database_failures = LogOnce(logger, "The health check's database query", traceback=True)


def _redis_ok() -> bool:
    import redis

    try:
        return bool(redis.Redis.from_url(settings.REDIS_URL, socket_timeout=1).ping())
    except redis.RedisError:
        return False


def limited_login(view: Callable[..., HttpResponse]) -> Callable[..., HttpResponse]:
    """Wrap a login form view with the limits /api/auth has: past them a POST gets 429, right password or not."""

    @functools.wraps(view)
    def login(request: HttpRequest, *args: object, **kwargs: object) -> HttpResponse:
        if request.method != "POST":
            return view(request, *args, **kwargs)
        username = str(request.POST.get("username", ""))[:200]
        address = request.META.get("REMOTE_ADDR", "")
        retry = bruteforce.blocked("user", username, address)
        if retry:
            response = HttpResponse(
                f"Too many failed logins; try again in {math.ceil(retry)} s.\n", status=429, content_type="text/plain"
            )
            response["Retry-After"] = str(math.ceil(retry))
            return response
        response = view(request, *args, **kwargs)
        # A login form redirects when it logs in and shows itself again (200) when it does not;
        # anything else (a CSRF refusal) never reached the password check.
        if response.status_code in (200, 302):
            bruteforce.attempted("user", username, address, response.status_code == 302)
        return response

    return login
