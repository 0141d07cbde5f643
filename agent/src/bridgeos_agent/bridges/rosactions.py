"""rosbridge v2's action ops for one client, as rosbridge_suite's ROS 2 branch defines them.

``send_action_goal`` and ``cancel_action_goal`` come in; ``action_feedback`` (when the goal asked
for it) and one ``action_result`` per goal go out. The result carries the goal's final status
(action_msgs/GoalStatus: 4 succeeded, 5 canceled, 6 aborted) with ``result: true`` whenever the
server gave a result, as rosbridge_suite does; a goal that never ran (no server, a goal that does not
fit its type, a rejection, a ROS 1 graph) gets a status error and ``result: false`` with status 0,
which roslibpy's ActionClient hands to its errback.
"""

from __future__ import annotations

import asyncio
import itertools
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from bridgeos_agent.bridges.graph import BridgeError, GoalOutcome, GraphActionGoal
from bridgeos_agent.bridges.rosbridgewire import Fail, count_field, name_field, text_field

if TYPE_CHECKING:
    from bridgeos_agent.bridges.rosbridge import RosbridgeSession

__all__ = ["RosActions"]

MAX_GOALS_IN_FLIGHT = 64  # goals one client may have running at once
GOAL_TIMEOUT = 10.0  # how long a server has to accept or reject a goal
CANCEL_TIMEOUT = 10.0  # how long a server has to answer a cancel
CLOSE_CANCEL_TIMEOUT = 2.0  # how long a leaving client's goals are given to be cancelled
ENDED_KEPT = 256  # ids of ended goals remembered, so a late cancel is told apart from a wrong id
STATUS_UNKNOWN = 0
COMPRESSIONS = ("none", "cbor")
SERVER_OPS = ("advertise_action", "unadvertise_action", "action_feedback", "action_result")


@dataclass
class _Goal:
    key: str
    name: str  # the action's full name
    ident: Any  # the client's id, echoed in every frame about the goal (None: the client gave none)
    action: str  # the action as the client spelled it
    compression: str
    fragment_size: int | None
    handle: GraphActionGoal | None = None  # once the server accepted it
    cancel_asked: bool = False
    task: asyncio.Task[None] | None = field(default=None, repr=False)


class RosActions:
    """The action goals one rosbridge client sent: each one a task that waits for its server's answer."""

    def __init__(self, session: RosbridgeSession) -> None:
        self.session = session
        self.graph = session.graph
        self._goals: dict[str, _Goal] = {}
        self._ended: deque[str] = deque(maxlen=ENDED_KEPT)
        self._cancels: set[asyncio.Task[None]] = set()
        self._anonymous = itertools.count(1)

    def handlers(self) -> dict[str, Callable[[dict[str, Any]], Awaitable[None]]]:
        """Return the session's handlers of the action ops, by op."""
        handlers: dict[str, Callable[[dict[str, Any]], Awaitable[None]]] = {
            "send_action_goal": self.send_goal,
            "cancel_action_goal": self.cancel_goal,
        }
        for op in SERVER_OPS:
            handlers[op] = self._refuse_server_op
        return handlers

    def goals(self) -> list[str]:
        """Return the keys of the goals in progress."""
        return list(self._goals)

    async def _refuse_server_op(self, message: dict[str, Any]) -> None:
        raise Fail(
            "this bridge sends goals to the graph's action servers (send_action_goal, cancel_action_goal) "
            "but does not serve actions for a client"
        )

    async def send_goal(self, message: dict[str, Any]) -> None:
        """Check a send_action_goal and start its goal; the answers come as the server gives them."""
        action = name_field(message, "action")
        action_type = text_field(message, "action_type", required=False)
        args = message.get("args", {})
        if isinstance(args, list) and not args:
            args = {}
        if not isinstance(args, dict):
            raise Fail("'args' must be an object with the goal's fields")
        feedback = message.get("feedback", False)
        if not isinstance(feedback, bool):
            raise Fail(f"'feedback' must be true or false, not {feedback!r}"[:200])
        compression = message.get("compression") or "none"
        if compression not in COMPRESSIONS:
            raise Fail(
                f"compression {compression!r} is not supported for actions: use one of {', '.join(COMPRESSIONS)}"
            )
        fragment_size = count_field(message, "fragment_size", 0) or None
        ident = message.get("id")
        if ident is not None and not isinstance(ident, str | int):
            raise Fail("'id' must be a string")
        key = str(ident) if ident is not None else f"anonymous:{next(self._anonymous)}"
        if key in self._goals:
            raise Fail(f"a goal with id {ident!r} is already in progress")
        if len(self._goals) >= MAX_GOALS_IN_FLIGHT:
            raise Fail(f"{MAX_GOALS_IN_FLIGHT} action goals are already running for this client")
        goal = _Goal(key, action, ident, message["action"], compression, fragment_size)
        self._goals[key] = goal
        goal.task = asyncio.get_running_loop().create_task(
            self._run(goal, action, action_type, args, feedback), name=f"rosbridge goal {key}"
        )

    async def _run(
        self, goal: _Goal, action: str, action_type: str | None, args: dict[str, Any], feedback: bool
    ) -> None:
        def heard(values: dict[str, Any]) -> None:
            if goal.key in self._goals:
                self._send(goal, {"op": "action_feedback", "action": goal.action, "values": values})

        try:
            try:
                goal.handle = await self.graph.send_action_goal(
                    action, action_type, args, heard if feedback else None, GOAL_TIMEOUT
                )
            except BridgeError as exc:
                # A goal that did not run is told by its result alone, as rosbridge_server does (roslibpy,
                # with no handler for status, would log one beside it as an error in the client's
                # application); a malformed goal is the client's error and also gets a status.
                if not isinstance(exc, GoalOutcome):
                    self.session.status("error", f"send_action_goal: {exc}", goal.ident)
                self._result(goal, STATUS_UNKNOWN, str(exc), succeeded=False)
                return
            if goal.cancel_asked:  # the cancel came while the server was deciding on the goal
                self._start_cancel(goal)
            try:
                status, values = await goal.handle.result()
            except BridgeError as exc:
                self._result(goal, STATUS_UNKNOWN, str(exc), succeeded=False)
                return
            self._result(goal, status, values, succeeded=True)
        finally:
            if self._goals.get(goal.key) is goal:
                del self._goals[goal.key]
                self._ended.append(goal.key)

    def _result(self, goal: _Goal, status: int, values: Any, *, succeeded: bool) -> None:
        self._send(
            goal,
            {"op": "action_result", "action": goal.action, "values": values, "status": status, "result": succeeded},
        )

    def _send(self, goal: _Goal, message: dict[str, Any]) -> None:
        if goal.ident is not None:
            message["id"] = goal.ident
        self.session.send(message, compression=goal.compression, fragment_size=goal.fragment_size)

    async def cancel_goal(self, message: dict[str, Any]) -> None:
        """Ask the server of one of the client's goals to cancel it; its action_result tells the outcome."""
        ident = message.get("id")
        if not isinstance(ident, str | int) or isinstance(ident, bool):
            raise Fail("'id' must be the id the goal was sent with" if "id" in message else "'id' is missing")
        action = name_field(message, "action")
        key = str(ident)
        goal = self._goals.get(key)
        if goal is None:
            if key in self._ended:
                raise Fail(f"goal {ident!r} has already ended", "warning")
            raise Fail(f"no goal with id {ident!r} is in progress")
        if goal.name != action:
            raise Fail(f"goal {ident!r} was sent to {goal.action}, not {message['action']}")
        goal.cancel_asked = True
        if goal.handle is not None:
            self._start_cancel(goal)

    def _start_cancel(self, goal: _Goal) -> None:
        task = asyncio.get_running_loop().create_task(self._cancel(goal), name=f"rosbridge cancel {goal.key}")
        self._cancels.add(task)
        task.add_done_callback(self._cancels.discard)

    async def _cancel(self, goal: _Goal) -> None:
        assert goal.handle is not None
        try:
            await goal.handle.cancel(CANCEL_TIMEOUT)
        except BridgeError as exc:
            self.session.status("error", f"cancel_action_goal: {exc}", goal.ident)

    async def close(self) -> None:
        """Cancel the client's goals in the graph: nobody is left to hear how they end."""
        goals = list(self._goals.values())
        self._goals.clear()
        tasks = [goal.task for goal in goals if goal.task is not None] + list(self._cancels)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        accepted = [goal.handle for goal in goals if goal.handle is not None]
        await asyncio.gather(*(handle.cancel(CLOSE_CANCEL_TIMEOUT) for handle in accepted), return_exceptions=True)
