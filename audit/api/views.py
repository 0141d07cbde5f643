"""`GET /api/audit`: the trail of the organizations you administer (staff: all), filtered, paged or exported."""

from __future__ import annotations

import csv
import json
from collections.abc import Iterator
from typing import Any

from django.db.models import QuerySet
from django.http import HttpResponseBase, StreamingHttpResponse
from drf_spectacular.utils import extend_schema
from rest_framework.renderers import JSONRenderer
from rest_framework.request import Request
from rest_framework.response import Response
from rest_framework.utils.urls import replace_query_param
from rest_framework.views import APIView

from robots.access import Actor, actor_of
from teams.roles import Right

from ..models import AuditEntry
from .serializers import FIELDS, AuditEntrySerializer, AuditQuerySerializer

EXPORT_CHUNK = 2000
# A spreadsheet runs a cell that starts with one of these as a formula (CSV injection): a user's
# or robot's name written into the trail must open as text.
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")


def visible_entries(actor: Actor) -> QuerySet[AuditEntry]:
    """Return the entries a request may read: staff all, others those of organizations they administer."""
    entries = AuditEntry.objects.all()
    ids = actor.organization_ids()
    if ids is None:
        return entries
    return entries.filter(organization_id__in=[org for org in ids if actor.may(org, Right.ADMINISTER)])


def _csv_rows(entries: QuerySet[AuditEntry]) -> Iterator[str]:
    """Yield a CSV header and then one line per entry."""

    class Line:
        def write(self, value: str) -> str:
            return value

    writer = csv.writer(Line())
    yield writer.writerow(FIELDS)
    for row in entries.values_list(*FIELDS).iterator(chunk_size=EXPORT_CHUNK):
        values = list(row)
        values[1] = values[1].isoformat()
        values[12] = json.dumps(values[12], sort_keys=True)
        yield writer.writerow([as_text(value) for value in values])


def as_text(value: Any) -> Any:
    """Return a CSV cell that a spreadsheet shows as text, never runs as a formula."""
    return "'" + value if isinstance(value, str) and value.startswith(FORMULA_STARTS) else value


def _json_rows(entries: QuerySet[AuditEntry]) -> Iterator[str]:
    """Yield one JSON array of every entry, a piece at a time."""
    yield "["
    for index, entry in enumerate(entries.iterator(chunk_size=EXPORT_CHUNK)):
        yield ("," if index else "") + json.dumps(AuditEntrySerializer(entry).data)
    yield "]\n"


class AuditListView(APIView):
    """Read the audit trail: filters, pages newest first (`next` follows on), CSV or JSON export."""

    def perform_content_negotiation(self, request: Request, force: bool = False) -> tuple[Any, str]:
        # `format` picks this view's export, not one of DRF's renderers.
        return JSONRenderer(), JSONRenderer.media_type

    @extend_schema(parameters=[AuditQuerySerializer], responses={200: AuditEntrySerializer(many=True)})
    def get(self, request: Request) -> HttpResponseBase:
        form = AuditQuerySerializer(data=request.query_params)
        form.is_valid(raise_exception=True)
        query = form.validated_data
        entries = form.filtered(visible_entries(actor_of(request))).order_by("-id")
        if query["format"] == "csv" or query["download"]:
            csv_wanted = query["format"] == "csv"
            response = StreamingHttpResponse(
                _csv_rows(entries) if csv_wanted else _json_rows(entries),
                content_type="text/csv; charset=utf-8" if csv_wanted else "application/json",
            )
            response["Content-Disposition"] = f'attachment; filename="audit.{query["format"]}"'
            return response
        if "before" in query:
            entries = entries.filter(id__lt=query["before"])
        page = list(entries[: query["limit"] + 1])
        more = len(page) > query["limit"]
        page = page[: query["limit"]]
        url = request.build_absolute_uri()
        following = replace_query_param(url, "before", page[-1].id) if more else None
        return Response({"next": following, "results": AuditEntrySerializer(page, many=True).data})
