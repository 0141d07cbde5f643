"""Site-wide views: the operator dashboard's entry page and the health check."""

from __future__ import annotations

from django.conf import settings
from django.contrib.auth.decorators import login_required
from django.db import connection
from django.db.models import Count
from django.http import HttpRequest, HttpResponse
from django.shortcuts import render
from drf_spectacular.utils import OpenApiResponse, extend_schema
from rest_framework.decorators import api_view, permission_classes
from rest_framework.permissions import AllowAny
from rest_framework.request import Request
from rest_framework.response import Response

from robots.models import Robot


def visible_robots(user):
    """Return the robots a user may see: their own, or all for staff."""
    robots = Robot.objects.all()
    return robots if user.is_staff else robots.filter(owner=user)


@login_required
def index(request: HttpRequest) -> HttpResponse:
    """Show the fleet the user may see."""
    robots = visible_robots(request.user).annotate(skill_count=Count("skills")).order_by("id")
    return render(request, "dashboard/index.html", {"robots": robots})


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
        return True
    except Exception:
        return False


def _redis_ok() -> bool:
    import redis

    try:
        return bool(redis.Redis.from_url(settings.REDIS_URL, socket_timeout=1).ping())
    except redis.RedisError:
        return False
