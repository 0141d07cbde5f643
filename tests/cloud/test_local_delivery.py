"""Messages between ends in this process skip the channel layer, but only on the loop those ends run on."""

from __future__ import annotations

import asyncio
import threading

from robots.local import local_consumer, register_local, unregister_local


class Mailbox:
    def __init__(self, channel_name: str) -> None:
        self.channel_name = channel_name
        self.got: list[dict] = []

    async def dispatch(self, message: dict) -> None:
        self.got.append(message)


def test_a_registered_end_is_found_on_its_own_loop_only() -> None:
    box = Mailbox("specific.test!local-1")

    async def register_and_find() -> object:
        register_local(box)
        return local_consumer(box.channel_name)

    assert asyncio.run(register_and_find()) is box

    found_elsewhere: list[object] = []

    async def find() -> None:
        found_elsewhere.append(local_consumer(box.channel_name))

    # Another loop (a thread's own, as async_to_sync makes outside daphne) must use the channel layer.
    thread = threading.Thread(target=lambda: asyncio.run(find()))
    thread.start()
    thread.join()
    assert found_elsewhere == [None]


def test_an_unregistered_end_is_not_found() -> None:
    box = Mailbox("specific.test!local-2")

    async def cycle() -> tuple[object, object]:
        register_local(box)
        before = local_consumer(box.channel_name)
        unregister_local(box)
        return before, local_consumer(box.channel_name)

    assert asyncio.run(cycle()) == (box, None)
