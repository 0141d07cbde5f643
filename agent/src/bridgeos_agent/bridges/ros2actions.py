"""ROS 2 actions for the bridges: goals sent to the graph's action servers through rclpy action clients.

The action clients belong to the bridge's node and run on its executor thread; their futures are
handed to the event loop. A goal the bridge sends is a ``Ros2ActionGoal``: its result to wait for,
and its cancel. rclpy calls the feedback callback on the executor thread: the feedback is made plain
data there and passed to the loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from typing import Any

from bridgeos_agent.bridges.graph import BridgeError, GoalOutcome

__all__ = ["SERVER_WAIT_S", "Ros2ActionGoal", "Ros2Actions"]

SERVER_WAIT_S = 2.0  # how long a goal waits for its action server to be discovered before it is refused
CANCEL_CODES = {
    1: "the server rejected the cancel",
    2: "the server does not know the goal",
    3: "the goal has already ended",
}


def _settle(loop: asyncio.AbstractEventLoop, future: Any, what: str) -> asyncio.Future[Any]:
    """Return an asyncio future that settles, on ``loop``, when an rclpy future does."""
    answer: asyncio.Future[Any] = loop.create_future()

    def settle(done: Any) -> None:
        if answer.done():
            return
        if done.exception() is not None:
            answer.set_exception(BridgeError(f"{what}: {done.exception()}"))
        else:
            answer.set_result(done.result())

    def from_executor(done: Any) -> None:
        with contextlib.suppress(RuntimeError):  # the loop has closed: nobody waits any more
            loop.call_soon_threadsafe(settle, done)

    future.add_done_callback(from_executor)
    return answer


class Ros2ActionGoal:
    """A goal an action server of the graph accepted: wait for its result, or cancel it."""

    def __init__(self, loop: asyncio.AbstractEventLoop, name: str, handle: Any) -> None:
        self.name = name
        self.loop = loop
        self.handle = handle
        # Asked for at once: the server keeps a result only for a while after the goal ends.
        self._result = _settle(loop, handle.get_result_async(), f"{name}: the result")

    async def result(self) -> tuple[int, dict[str, Any]]:
        """Wait for the goal to end; return its status (action_msgs/GoalStatus) and its result."""
        from bridgeos_agent.bridges.ros2graph import message_to_plain

        response = await asyncio.shield(self._result)
        return int(response.status), message_to_plain(response.result)

    async def cancel(self, timeout: float) -> None:
        """Ask the server to cancel the goal; raise BridgeError with its reason when it will not."""
        try:
            response = await asyncio.wait_for(
                _settle(self.loop, self.handle.cancel_goal_async(), f"{self.name}: cancel"), timeout
            )
        except TimeoutError:
            raise BridgeError(f"{self.name} did not answer the cancel within {timeout:g} s") from None
        code = int(response.return_code)
        if code:
            raise BridgeError(f"{self.name}: {CANCEL_CODES.get(code, f'cancel refused (code {code})')}")


class Ros2Actions:
    """The action clients of the bridge's node, one per action and type, made on a goal's first use."""

    def __init__(self, node: Any, group: Any, loop: asyncio.AbstractEventLoop) -> None:
        self.node = node
        self.group = group
        self.loop = loop
        self._clients: dict[tuple[str, str], Any] = {}

    def known(self) -> dict[str, list[str]]:
        """Return every action of the graph (servers' and clients') with its types."""
        from rclpy.action import get_action_names_and_types

        return dict(get_action_names_and_types(self.node))

    def servers(self) -> dict[str, str]:
        """Return the actions a server serves now (it publishes the status topic), with their types."""
        return {
            name: types[0]
            for name, types in self.known().items()
            if types and self.node.count_publishers(f"{name}/_action/status")
        }

    async def send_goal(
        self,
        name: str,
        type_: str | None,
        goal: dict[str, Any],
        feedback: Callable[[dict[str, Any]], None] | None,
        timeout: float,
    ) -> Ros2ActionGoal:
        """Send a goal; return once its server accepted it, or raise BridgeError with the reason."""
        from bridgeos_agent.bridges.ros2graph import fill_message, message_to_plain, ros2_name
        from bridgeos_agent.ros2graph import Ros2TypeError, interface_class

        known = self.known().get(name) or []
        action_type = ros2_name(type_, "action") if type_ else (known[0] if known else None)
        if action_type is None:
            raise GoalOutcome(f"no action server answers {name} (and without 'action_type' its type is unknown)")
        if known and action_type not in known:
            raise BridgeError(f"{name} is of type {known[0]}, not {action_type}")
        try:
            cls: Any = interface_class(action_type, "action")
        except Ros2TypeError as exc:
            raise BridgeError(f"unknown action type {action_type}: {exc}") from None
        message = cls.Goal()
        fill_message(message, goal, action_type + ".Goal")  # a goal that does not fit is refused before anything

        client, created = self._client(name, action_type, cls)
        deadline = time.monotonic() + min(timeout, SERVER_WAIT_S)
        while not client.server_is_ready():
            if time.monotonic() > deadline:
                if created:  # the graph is left as it was: no action client of ours lingers
                    self._drop(name, action_type)
                raise GoalOutcome(f"no action server answers {name}")
            await asyncio.sleep(0.05)

        loop = self.loop

        def heard(message: Any) -> None:
            plain = message_to_plain(message.feedback)
            with contextlib.suppress(RuntimeError):
                loop.call_soon_threadsafe(feedback, plain)  # type: ignore[arg-type]

        sent = client.send_goal_async(message, feedback_callback=heard if feedback is not None else None)
        try:
            handle = await asyncio.wait_for(_settle(loop, sent, f"{name}: the goal"), timeout)
        except TimeoutError:
            # Accepted after all, later: nobody waits for it, so it is cancelled then.
            sent.add_done_callback(_cancel_late)
            raise GoalOutcome(f"{name} did not answer the goal within {timeout:g} s") from None
        except asyncio.CancelledError:  # the client left while the server was deciding
            sent.add_done_callback(_cancel_late)
            raise
        if not handle.accepted:
            raise GoalOutcome(f"{name} rejected the goal")
        return Ros2ActionGoal(loop, name, handle)

    def _client(self, name: str, action_type: str, cls: Any) -> tuple[Any, bool]:
        from rclpy.action import ActionClient

        client = self._clients.get((name, action_type))
        if client is not None:
            return client, False
        try:
            client = ActionClient(self.node, cls, name, callback_group=self.group)
        except Exception as exc:  # rclpy rejects bad names with its own exceptions
            raise BridgeError(f"cannot send goals to {name}: {exc}") from None
        self._clients[(name, action_type)] = client
        return client, True

    def _drop(self, name: str, action_type: str) -> None:
        client = self._clients.pop((name, action_type), None)
        if client is not None:
            with contextlib.suppress(Exception):
                client.destroy()

    def close(self) -> None:
        """Destroy every action client."""
        for name, action_type in list(self._clients):
            self._drop(name, action_type)


def _cancel_late(done: Any) -> None:
    handle = done.result() if done.exception() is None else None
    if handle is not None and handle.accepted:
        handle.cancel_goal_async()
