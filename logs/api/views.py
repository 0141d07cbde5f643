"""The Robot API about component logs: a robot's lines, filtered and paged, and their download."""

from __future__ import annotations

import itertools
from typing import Any

from django.http import HttpResponse
from drf_spectacular.types import OpenApiTypes
from drf_spectacular.utils import OpenApiParameter, OpenApiResponse, extend_schema
from rest_framework.exceptions import ValidationError
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from robots.api.views import robot_of

from .. import services
from .serializers import LogLineSerializer, LogPageSerializer, LogQuerySerializer

MAX_DOWNLOAD_LINES = 500_000
PARAMETERS = [
    OpenApiParameter("skill", str),
    OpenApiParameter("component", str),
    OpenApiParameter("location", str, enum=["robot", "cloud"]),
    OpenApiParameter("since", str, description="ISO 8601 time or unix seconds."),
    OpenApiParameter("until", str, description="ISO 8601 time or unix seconds."),
    OpenApiParameter(
        "level", str, enum=["debug", "info", "warning", "error", "critical"], description="Minimum level."
    ),
    OpenApiParameter("q", str, description="Case-insensitive substring (a regular expression with regex=true)."),
    OpenApiParameter("regex", bool),
]
PAGE_PARAMETERS = [
    OpenApiParameter("order", str, enum=["desc", "asc"], description="desc (default): newest first."),
    OpenApiParameter("limit", int, description="1 to 1000 (default 200)."),
    OpenApiParameter("cursor", str, description="The `next` link's cursor."),
]


def query_of(request: Request) -> tuple[services.LogFilters, dict[str, Any]]:
    """Validate the query string; return the filters and the paging options."""
    form = LogQuerySerializer(data=request.query_params.dict())
    form.is_valid(raise_exception=True)
    data = form.validated_data
    filters = services.LogFilters(
        **{key: data.get(key) for key in ("skill", "component", "location", "since", "until", "level", "q")},
        regex=data["regex"],
    )
    return filters, data


def run(query: Any) -> Any:
    """Run a query, answering a regular expression the database refuses as a 400 naming `q`."""
    try:
        return query()
    except services.BadQuery as exc:
        raise ValidationError({"q": [f"Not a regular expression the database accepts: {exc}"]}) from None


class LogListView(APIView):
    """A robot's component logs, filtered, newest first by default, a page at a time."""

    @extend_schema(
        parameters=PARAMETERS + PAGE_PARAMETERS,
        responses={200: LogPageSerializer, 400: OpenApiResponse(), 404: OpenApiResponse()},
    )
    def get(self, request: Request, robot_id: str) -> Response:
        robot = robot_of(request, robot_id)
        filters, options = query_of(request)
        rows, cursor = run(
            lambda: services.page_of_lines(
                robot.id, filters, order=options["order"], limit=options["limit"], cursor=options.get("cursor")
            )
        )
        next_url = None
        if cursor is not None:
            params = request.query_params.copy()
            params["cursor"] = cursor
            next_url = request.build_absolute_uri(f"{request.path}?{params.urlencode()}")
        return Response(
            {
                "results": LogLineSerializer(rows, many=True).data,
                "next": next_url,
                "dropped": services.dropped_count(robot.id, filters),
            }
        )


class LogDownloadView(APIView):
    """A robot's component logs matching the filters as a text file, oldest first."""

    @extend_schema(
        parameters=PARAMETERS,
        responses={(200, "text/plain"): OpenApiTypes.STR, 400: OpenApiResponse(), 404: OpenApiResponse()},
    )
    def get(self, request: Request, robot_id: str) -> HttpResponse:
        robot = robot_of(request, robot_id)
        filters, _ = query_of(request)
        # Built whole, in this request's thread and database connection (a streamed body would be read
        # elsewhere); capped, and the cap said in a header.
        rows = run(lambda: list(itertools.islice(services.iter_lines(robot.id, filters), MAX_DOWNLOAD_LINES + 1)))
        response = HttpResponse(
            "".join(services.format_line(row) for row in rows[:MAX_DOWNLOAD_LINES]),
            content_type="text/plain; charset=utf-8",
        )
        response["Content-Disposition"] = f'attachment; filename="{robot.id}-logs.txt"'
        if len(rows) > MAX_DOWNLOAD_LINES:
            response["X-Log-Truncated"] = f"only the first {MAX_DOWNLOAD_LINES} lines; narrow the time range"
        return response
