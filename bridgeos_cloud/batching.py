"""Gather requests that arrive together into one call in a database thread (connect storms)."""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Callable, Hashable
from typing import Generic, TypeVar

from channels.db import database_sync_to_async

CLOSE_WAIT_S = 10.0

Request = TypeVar("Request")
Outcome = TypeVar("Outcome")


class Batcher(Generic[Request, Outcome]):
    """Run a sync function over the requests that queued up while its previous call ran.

    The ORM runs on one thread per process, so a thousand callers each making their own round
    trips wait in one line; batched, they share a few round trips. No timer: a lone request
    runs at once, and under load each batch holds whatever arrived during the last one.
    """

    def __init__(
        self,
        function: Callable[[list[Request]], list[Outcome]],
        *,
        key: Callable[[Request], Hashable],
        max_batch: int = 500,
    ) -> None:
        self.function = function
        self.key = key
        self.max_batch = max_batch
        self.pending: deque[tuple[Request, asyncio.Future[Outcome]]] = deque()
        self._drainer: asyncio.Task | None = None
        self.closed = False

    async def submit(self, request: Request) -> Outcome:
        """Queue a request and return its outcome once its batch ran."""
        future: asyncio.Future[Outcome] = asyncio.get_running_loop().create_future()
        self.pending.append((request, future))
        if self._drainer is None or self._drainer.done():
            self._drainer = asyncio.ensure_future(self._drain())
        return await future

    def _next_batch(self) -> list[tuple[Request, asyncio.Future[Outcome]]]:
        """Take up to max_batch waiting requests with distinct keys; a repeated key waits for the next batch."""
        batch, repeated, keys = [], [], set()
        while self.pending and len(batch) < self.max_batch:
            request, future = self.pending.popleft()
            if future.done():
                continue  # its caller gave up
            key = self.key(request)
            (repeated if key in keys else batch).append((request, future))
            keys.add(key)
        self.pending.extendleft(reversed(repeated))
        return batch

    async def _drain(self) -> None:
        while self.pending and not self.closed:
            batch = self._next_batch()
            if not batch:
                continue
            try:
                outcomes = await database_sync_to_async(self.function)([request for request, _ in batch])
            except Exception as exc:
                for _, future in batch:
                    if not future.done():
                        future.set_exception(exc)
            else:
                for (_, future), outcome in zip(batch, outcomes, strict=True):
                    if not future.done():
                        future.set_result(outcome)

    async def close(self) -> None:
        """Stop taking batches; waiting callers are cancelled, the batch being applied finishes."""
        self.closed = True
        while self.pending:
            self.pending.popleft()[1].cancel()
        if self._drainer is not None and not self._drainer.done():
            # On this loop, which it still needs: its commit broadcasts through it, and a database
            # thread left waiting for a stopped loop would keep the process from exiting.
            await asyncio.wait([self._drainer], timeout=CLOSE_WAIT_S)
