"""The dashboard's audit page: the trail you may read, filtered, with an export link."""

from __future__ import annotations

from django.contrib.auth.decorators import login_required
from django.http import HttpRequest, HttpResponse
from django.shortcuts import render
from django.utils.http import urlencode

from robots.access import actor_of

from .api.serializers import AuditQuerySerializer
from .api.views import visible_entries
from .choices import Door, Outcome

FILTERS = ("since", "until", "actor", "action", "door", "outcome", "robot", "organization")


@login_required
def audit_page(request: HttpRequest) -> HttpResponse:
    """Show the newest entries matching the filters, a page at a time, and link their CSV export."""
    given = {key: request.GET[key] for key in (*FILTERS, "before") if request.GET.get(key)}
    form = AuditQuerySerializer(data=given)
    entries: list = []
    following = ""
    if form.is_valid():
        found = form.filtered(visible_entries(actor_of(request))).order_by("-id")
        if "before" in form.validated_data:
            found = found.filter(id__lt=form.validated_data["before"])
        entries = list(found[:101])
        if len(entries) > 100:
            entries = entries[:100]
            following = "?" + urlencode({**given, "before": entries[-1].id})
    filters = {key: value for key, value in given.items() if key != "before"}
    return render(
        request,
        "audit/audit.html",
        {
            "page": "audit",
            "entries": entries,
            "errors": form.errors,
            "filters": {key: filters.get(key, "") for key in FILTERS},
            "doors": Door.choices,
            "outcomes": Outcome.choices,
            "export": "/api/audit?" + urlencode({**filters, "format": "csv"}),
            "next": following,
        },
    )
