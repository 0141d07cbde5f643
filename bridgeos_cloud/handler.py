"""Django's ASGI handler with each request's synchronous work on a fixed pool of threads."""

from __future__ import annotations

import asyncio
from concurrent.futures import ThreadPoolExecutor

from asgiref.sync import sync_to_async
from django.core import signals
from django.core.exceptions import RequestAborted
from django.core.handlers.asgi import ASGIHandler, get_script_prefix
from django.db import close_old_connections
from django.http import HttpRequest, HttpResponse
from django.urls import set_script_prefix

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


class PooledASGIHandler(ASGIHandler):
    """Serve HTTP like Django's ASGIHandler, but run the (all-sync) request path on a thread pool.

    Stock Django gives every request a thread-sensitive context (a new one-thread executor,
    and in current asgiref a second thread to join it) and sends the request signals through
    one process-wide thread, twice per request. At 100 requests/s that churn and that single
    funnel made p99 latency ten times the median. Here a fixed pool does what a threaded WSGI
    server does: a worker sends request_started, runs the middleware chain and the view, and
    hands its database connection back to the pool before the response is sent.
    """

    def __init__(self, threads: int, write_threads: int | None = None) -> None:
        super().__init__()
        # Rebuild the chain as plain sync code: the pool threads call it directly.
        self.load_middleware(is_async=False)
        pool = ThreadPoolExecutor(max_workers=threads, thread_name_prefix="http")
        # Writes have a pool of their own: a command waits seconds for its robot's reply while
        # holding its thread, and a burst of them must not leave reads queued behind. A larger one:
        # with as many threads as reads, commands to silent robots queued the next ones past their
        # own wait, until the robot had left (409 after a minute instead of 504 after the wait).
        # A waiting command holds no database connection (robots.api.commands.relay).
        write_pool = ThreadPoolExecutor(max_workers=write_threads or threads, thread_name_prefix="http-write")
        # Through asgiref, so async_to_sync in a view (commands relayed over the channel
        # layer) runs on the server's event loop, not on a new loop per thread.
        self._in_pool = lambda function: sync_to_async(function, thread_sensitive=False, executor=pool)
        self._in_write_pool = lambda function: sync_to_async(function, thread_sensitive=False, executor=write_pool)

    async def __call__(self, scope, receive, send) -> None:  # type: ignore[no-untyped-def]
        if scope["type"] != "http":
            raise ValueError(f"Django can only handle ASGI/HTTP connections, not {scope['type']}.")
        await self.handle(scope, receive, send)

    async def handle(self, scope, receive, send) -> None:  # type: ignore[no-untyped-def]
        try:
            body_file = await self.read_body(receive)
        except RequestAborted:
            return
        set_script_prefix(get_script_prefix(scope))
        request, error_response = self.create_request(scope, body_file)
        if request is None:
            body_file.close()
            await self.send_response(error_response, send)
            await self._in_pool(error_response.close)()
            return
        try:
            in_pool = self._in_pool if request.method in SAFE_METHODS else self._in_write_pool
            response = await in_pool(self._respond)(request, scope)
            response._handler_class = self.__class__
            try:
                await self.send_response(response, send)
            except asyncio.CancelledError:
                pass  # the client went away while the response was being sent
            await self._in_pool(response.close)()
        finally:
            body_file.close()

    def _respond(self, request: HttpRequest, scope: dict) -> HttpResponse:
        signals.request_started.send(sender=self.__class__, scope=scope)
        try:
            return self.get_response(request)
        finally:
            # CONN_MAX_AGE=0 with the pool: this thread's connection goes back to the pool now.
            close_old_connections()
