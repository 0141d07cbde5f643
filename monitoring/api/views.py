"""The Robot API's monitoring routes: /api/database/query and the event log."""

from __future__ import annotations

import re

from django.db import DataError, OperationalError
from django.db.models import QuerySet
from drf_spectacular.utils import OpenApiParameter, OpenApiResponse, extend_schema
from rest_framework import generics, status
from rest_framework.exceptions import ValidationError
from rest_framework.pagination import LimitOffsetPagination
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.views import APIView

from bridgeos_agent.skillconfig import SLUG_PATTERN
from robots.access import actor_of, robot_scope, visible_robots

from .. import services
from ..models import Event
from .serializers import EventSerializer, MetricRowSerializer, QueryResultSerializer, QuerySerializer


def events_of(request: Request, filters: dict) -> QuerySet[Event]:
    """Return the events the user may see (staff: also fleet-wide events) matching filters."""
    return services.events_matching(filters, robot_scope(actor_of(request)))


class DatabaseQueryView(APIView):
    """Query the latest metrics and activity of your robots: filters, time range, aggregation per bucket."""

    @extend_schema(request=QuerySerializer, responses={200: QueryResultSerializer, 400: OpenApiResponse()})
    def post(self, request: Request) -> Response:
        form = QuerySerializer(data=request.data)
        form.is_valid(raise_exception=True)
        query = form.validated_data
        robots = visible_robots(actor_of(request))
        if query.get("robots"):
            robots = robots.filter(id__in=query["robots"])
            unknown = set(query["robots"]) - set(robots.values_list("id", flat=True))
            if unknown:
                raise ValidationError({"robots": [f"No robot {robot_id!r}." for robot_id in sorted(unknown)]})
        if query["kind"] == "events":
            events = events_of(request, query)[: query["limit"]]
            return Response({"kind": "events", "results": EventSerializer(events, many=True).data})
        try:
            rows = services.aggregate_metrics(
                list(robots.values_list("id", flat=True)),
                since=query["since"],
                until=query["until"],
                aggregate=query["aggregate"],
                bucket_seconds=query.get("bucket"),
                names=query.get("names"),
                skill=query.get("skill"),
                component=query.get("component"),
                limit=query["limit"],
            )
        except OperationalError:
            return Response(
                {"detail": "The query took too long; narrow the time range, robots or names."},
                status=status.HTTP_503_SERVICE_UNAVAILABLE,
            )
        except DataError:
            # Points are finite but may be near the largest float, and PostgreSQL refuses a sum past it.
            raise ValidationError({"aggregate": ["The values overflow this aggregate; choose another."]}) from None
        return Response({"kind": "metrics", "results": MetricRowSerializer(rows, many=True).data})


class EventPagination(LimitOffsetPagination):
    # Unbounded, a huge ?limit= overflows PostgreSQL's bigint LIMIT.
    max_limit = 1000


class EventListView(generics.ListAPIView):
    """The event log of your robots, newest first, filtered and paginated."""

    serializer_class = EventSerializer
    pagination_class = EventPagination

    @extend_schema(
        parameters=[
            OpenApiParameter("robot", str),
            OpenApiParameter("skill", str),
            OpenApiParameter("component", str),
            OpenApiParameter("kind", str),
            OpenApiParameter("level", str, enum=services.LEVEL_ORDER, description="Minimum level."),
            OpenApiParameter("since", str, description="ISO 8601 time."),
            OpenApiParameter("until", str, description="ISO 8601 time."),
        ]
    )
    def get(self, request: Request, *args: object, **kwargs: object) -> Response:
        return super().get(request, *args, **kwargs)

    def get_queryset(self) -> QuerySet[Event]:
        params = self.request.query_params
        form = QuerySerializer(
            data={
                "kind": "events",
                **({"robots": [params["robot"]]} if "robot" in params else {}),
                **{key: params[key] for key in ("skill", "component", "level", "since", "until") if key in params},
            }
        )
        form.is_valid(raise_exception=True)
        filters = dict(form.validated_data)
        # The log is browsed without a default window: only the bounds the caller gave apply.
        for bound in ("since", "until"):
            if bound not in params:
                filters.pop(bound)
        if "kind" in params:
            if not re.fullmatch(SLUG_PATTERN, params["kind"]):
                raise ValidationError({"kind": ["An event kind, such as skill_status."]})
            filters["event"] = params["kind"]
        if getattr(self, "swagger_fake_view", False):
            return Event.objects.none()
        return events_of(self.request, filters)
