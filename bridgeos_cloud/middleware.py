"""Middleware of the project."""

from __future__ import annotations

from collections.abc import Callable

from django.http import HttpRequest, HttpResponse


class SyncChain:
    """Make Django run the whole middleware chain synchronously, in one thread per request.

    Django's stock middleware can run async, but then each of its hooks is a separate hop
    to a worker thread (about 30 per request here, ~5 ms of CPU under daphne). A sync-only
    middleware innermost makes every middleware above it run sync: one hop per request.
    """

    sync_capable = True
    async_capable = False

    def __init__(self, get_response: Callable[[HttpRequest], HttpResponse]) -> None:
        self.get_response = get_response

    def __call__(self, request: HttpRequest) -> HttpResponse:
        return self.get_response(request)
