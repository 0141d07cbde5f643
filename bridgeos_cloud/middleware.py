"""Middleware of the project."""

from __future__ import annotations

import gzip
from collections.abc import Callable

from django.http import HttpRequest, HttpResponse
from django.utils.cache import patch_vary_headers


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


class CompressLargeResponses:
    """Gzip large answers (the fleet's JSON) at level 1 for clients that accept it.

    A 100-robot fleet is ~700 KB of JSON; level 1 makes it ~25x smaller in ~2 ms (zlib lets
    other threads run meanwhile), so the event loop sends and clients read a fraction of it.
    Small answers are left alone: compressing them costs more than it saves.
    """

    sync_capable = True
    async_capable = False
    min_bytes = 32 * 1024

    def __init__(self, get_response: Callable[[HttpRequest], HttpResponse]) -> None:
        self.get_response = get_response

    def __call__(self, request: HttpRequest) -> HttpResponse:
        response = self.get_response(request)
        if (
            response.streaming
            or response.has_header("Content-Encoding")
            or len(response.content) < self.min_bytes
            or "gzip" not in request.META.get("HTTP_ACCEPT_ENCODING", "")
        ):
            return response
        patch_vary_headers(response, ("Accept-Encoding",))
        response.content = gzip.compress(response.content, compresslevel=1, mtime=0)
        response["Content-Length"] = str(len(response.content))
        response["Content-Encoding"] = "gzip"
        return response
