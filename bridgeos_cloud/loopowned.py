"""One owner for the objects that live as long as an event loop: the metric writer, the live feed, applied ids.

Each is created on first use in its loop (`loop_object`) and closed, newest first, when the
server shuts down (`close_loop_objects`, which the ASGI entry point hooks into daphne's shutdown).
"""

from __future__ import annotations

import asyncio
import logging
import weakref
from collections.abc import Callable
from typing import Any, Protocol, TypeVar

logger = logging.getLogger(__name__)

T = TypeVar("T", bound="Closable")


class Closable(Protocol):
    async def close(self) -> None: ...


_owned: weakref.WeakKeyDictionary[asyncio.AbstractEventLoop, dict[str, Any]] = weakref.WeakKeyDictionary()


def loop_object(name: str, create: Callable[[], T], *, usable: Callable[[T], bool] = lambda _: True) -> T:
    """Return the running loop's object called ``name``, creating it on first use (and again once not usable)."""
    owned = _owned.setdefault(asyncio.get_running_loop(), {})
    found = owned.get(name)
    if found is None or not usable(found):
        # Re-inserted, so the newest objects are closed first at shutdown.
        owned.pop(name, None)
        found = owned[name] = create()
    return found


async def close_loop_objects() -> None:
    """Close the running loop's objects, newest first; one that fails to close does not keep the others open."""
    owned = _owned.pop(asyncio.get_running_loop(), {})
    for name, thing in reversed(list(owned.items())):
        try:
            await thing.close()
        except Exception:
            logger.exception("closing the %s at shutdown failed", name)
    if owned:
        logger.info("closed %s", ", ".join(reversed(owned)))
