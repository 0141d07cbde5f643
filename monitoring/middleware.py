"""Time every HTTP request for Prometheus, labelled by route pattern (never the raw path)."""

from __future__ import annotations

import time
from collections.abc import Callable

from django.http import HttpRequest, HttpResponse

from .prometheus import HTTP_SECONDS

UNMATCHED = "unmatched"


class RequestLatency:
    """Observe each request's duration by route, method and status class."""

    sync_capable = True
    async_capable = False

    def __init__(self, get_response: Callable[[HttpRequest], HttpResponse]) -> None:
        self.get_response = get_response

    def __call__(self, request: HttpRequest) -> HttpResponse:
        started = time.perf_counter()
        response = self.get_response(request)
        match = request.resolver_match
        # The pattern, not the path: a path per robot would make a series per robot.
        route = (match.route or match.view_name or UNMATCHED) if match is not None else UNMATCHED
        method = request.method if request.method in ("GET", "POST", "PUT", "PATCH", "DELETE", "HEAD") else "OTHER"
        HTTP_SECONDS.labels(route, method, f"{response.status_code // 100}xx").observe(time.perf_counter() - started)
        return response
