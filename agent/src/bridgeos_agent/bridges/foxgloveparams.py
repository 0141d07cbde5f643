"""The Foxglove WebSocket ``parameters`` and ``parametersSubscribe`` capabilities on a robot's graph.

ROS 1 parameters are the master's (``/robot/gain``); ROS 2 parameters belong to nodes and are
named ``/node_name:parameter`` as rosbridge's rosapi names them. A subscribed parameter is polled
at a modest rate, and only while some client is subscribed to any; on ROS 2 a node's
``/parameter_events`` (when it publishes them) makes the poll come at once. A client's
``setParameters`` is checked whole before anything is set, and undone if the graph refuses part of
it, so a bad request changes nothing.
"""

from __future__ import annotations

import asyncio
import base64
import binascii
import contextlib
import logging
import math
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from bridgeos_agent.bridges.foxglovewire import WARNING, Fail, items_field
from bridgeos_agent.bridges.graph import BridgeError, BridgeGraph, GraphSubscription

if TYPE_CHECKING:
    from bridgeos_agent.bridges.foxglove import FoxgloveSession

__all__ = ["CAPABILITIES", "PARAM_POLL_S", "ParameterOps", "ParameterWatch", "encode_parameter"]

logger = logging.getLogger(__name__)

CAPABILITIES = ("parameters", "parametersSubscribe")
PARAM_POLL_S = 1.0  # how often subscribed parameters are read while anyone is subscribed
MAX_NAMES = 10_000  # parameter names one request may carry
TYPES = ("byte_array", "float64", "float64_array")
PARAMETER_EVENTS = ("/parameter_events", "rcl_interfaces/msg/ParameterEvent")
_UNSET = object()  # a setParameters entry without a value: unset the parameter


def encode_parameter(name: str, value: Any) -> dict[str, Any]:
    """Return one parameterValues entry: byte arrays in base64 and doubles marked, as the protocol asks."""
    if isinstance(value, bytes | bytearray | memoryview):
        return {"name": name, "value": base64.b64encode(bytes(value)).decode(), "type": "byte_array"}
    if isinstance(value, float):
        # JSON has no infinity or NaN: their spelling as text tells the client what the robot holds.
        return (
            {"name": name, "value": value, "type": "float64"}
            if math.isfinite(value)
            else {"name": name, "value": str(value)}
        )
    if isinstance(value, list) and value and all(isinstance(v, float) for v in value):
        if all(math.isfinite(v) for v in value):
            return {"name": name, "value": value, "type": "float64_array"}
    if isinstance(value, dict):
        return {"name": name, "value": _plain(value)}
    return {"name": name, "value": value}


def _plain(value: Any) -> Any:
    if isinstance(value, bytes | bytearray | memoryview):
        return base64.b64encode(bytes(value)).decode()
    if isinstance(value, dict):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_plain(item) for item in value]
    return value


def _names(message: dict[str, Any], key: str) -> list[str] | None:
    """Return the parameter names of a request, or None for 'all' (an empty or absent list)."""
    if message.get(key) is None:
        return None
    names = items_field(message, key)
    if len(names) > MAX_NAMES:
        raise Fail(f"'{key}' may name at most {MAX_NAMES} parameters")
    for index, name in enumerate(names):
        if not isinstance(name, str) or not name:
            raise Fail(f"'{key}[{index}]' must be a non-empty string, not {name!r}"[:200])
    return list(dict.fromkeys(names)) or None


def _request_id(message: dict[str, Any]) -> str | None:
    ident = message.get("id")
    if ident is not None and not isinstance(ident, str):
        raise Fail(f"'id' must be a string, not {ident!r}"[:200])
    return ident


def _decode_value(index: int, item: Any) -> tuple[str, Any]:
    """Return (name, value) of one setParameters entry, its value as the graph takes it (or _UNSET)."""
    where = f"parameters[{index}]"
    if not isinstance(item, dict):
        raise Fail(f"{where} must be an object with 'name' and 'value'")
    name, kind = item.get("name"), item.get("type")
    if not isinstance(name, str) or not name:
        raise Fail(f"{where}.name must be a non-empty string")
    if kind is not None and kind not in TYPES:
        raise Fail(f"{where}.type must be one of {', '.join(TYPES)}, not {kind!r}"[:200])
    if "value" not in item:  # the protocol's undefined: unset the parameter
        return name, _UNSET
    value = item["value"]
    if kind == "byte_array":
        if not isinstance(value, str):
            raise Fail(f"{where}.value must be base64 text for type byte_array")
        try:
            return name, base64.b64decode(value, validate=True)
        except (binascii.Error, ValueError):
            raise Fail(f"{where}.value is not base64") from None
    if kind == "float64":
        if not _number(value):
            raise Fail(f"{where}.value must be a number for type float64, not {value!r}"[:200])
        return name, float(value)
    if kind == "float64_array":
        if not isinstance(value, list) or not all(_number(v) for v in value):
            raise Fail(f"{where}.value must be an array of numbers for type float64_array")
        return name, [float(v) for v in value]
    if isinstance(value, bool | int | float | str):
        return name, value
    if isinstance(value, list) and (
        all(isinstance(v, bool) for v in value)
        or all(_number(v) for v in value)
        or all(isinstance(v, str) for v in value)
    ):
        return name, value
    raise Fail(f"{where}.value must be a number, a boolean, a string or an array of one of them, not {value!r}"[:200])


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _kind(value: Any) -> str:
    if isinstance(value, list):
        inner = {_kind(v) for v in value}
        return f"an array of {inner.pop()}s" if len(inner) == 1 else "an array"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, int):
        return "integer"
    if isinstance(value, float):
        return "double"
    if isinstance(value, str):
        return "string"
    if isinstance(value, bytes | bytearray):
        return "byte array"
    return type(value).__name__


def _fit(before: Any, value: Any) -> Any:
    """Return ``value`` as the parameter's own kind where no information is lost (2 for a double: 2.0)."""
    if isinstance(before, float) and _number(value):
        return float(value)
    if isinstance(before, list) and before and all(isinstance(v, float) for v in before):
        if isinstance(value, list) and all(_number(v) for v in value):
            return [float(v) for v in value]
    return value


async def set_parameters(graph: BridgeGraph, changes: list[tuple[str, Any]]) -> None:
    """Set (or unset) parameters, all of them or none: checked first, and undone if the graph refuses one."""
    before = await graph.get_params([name for name, _ in changes])
    checked = []
    for index, (name, value) in enumerate(changes):
        where = f"parameters[{index}] ({name})"
        if value is _UNSET:
            if name not in before:
                raise Fail(f"{where}: no such parameter to unset")
        elif name in before:
            value = _fit(before[name], value)
            if graph.ros_version == 2 and _kind(value) != _kind(before[name]):
                raise Fail(f"{where}: the node holds it as {_kind(before[name])}, not {_kind(value)}")
        elif graph.ros_version == 2:
            raise Fail(f"{where}: no such parameter (a ROS 2 node takes only the parameters it declared)")
        checked.append((name, value))
    done: list[str] = []
    for index, (name, value) in enumerate(checked):
        try:
            if value is _UNSET:
                await graph.delete_param(name)
            else:
                await graph.set_param(name, value)
        except (BridgeError, KeyError) as exc:
            stuck = await _restore(graph, done, before)
            told = f"could not restore {', '.join(stuck)}" if stuck else "nothing was changed"
            reason = f"no such parameter {name}" if isinstance(exc, KeyError) else str(exc)  # the graph names it
            raise Fail(f"parameters[{index}]: {reason}; {told}") from None
        done.append(name)


async def _restore(graph: BridgeGraph, names: list[str], before: dict[str, Any]) -> list[str]:
    stuck = []
    for name in reversed(names):
        try:
            if name in before:
                await graph.set_param(name, before[name])
            else:
                await graph.delete_param(name)
        except (BridgeError, KeyError):
            stuck.append(name)
    return stuck


class ParameterWatch:
    """The parameters clients are subscribed to, read every ``poll_s`` while there are any."""

    def __init__(self, graph: BridgeGraph, poll_s: float = PARAM_POLL_S) -> None:
        self.graph = graph
        self.poll_s = poll_s
        self.subscribers: dict[FoxgloveSession, set[str]] = {}
        self.values: dict[str, dict[str, Any]] = {}  # each watched parameter's last entry (absent: not set)
        self._poller: asyncio.Task[None] | None = None
        self._poll_now = asyncio.Event()
        self._events: GraphSubscription | None = None
        self.polls = 0

    def watched(self) -> set[str]:
        """Return the names some client is subscribed to."""
        return set().union(*self.subscribers.values()) if self.subscribers else set()

    async def subscribe(self, session: FoxgloveSession, names: list[str] | None) -> None:
        """Add parameters to a client's subscription (every parameter known now when None)."""
        wanted = names if names is not None else await self.graph.param_names()
        new = [name for name in wanted if name not in self.watched()]
        if new:
            # Read now, so the first poll reports changes from here on and not every value.
            current = await self.graph.get_params(new)
            for name in new:
                if name in current:
                    self.values[name] = encode_parameter(name, current[name])
        self.subscribers.setdefault(session, set()).update(wanted)
        if self._poller is None or self._poller.done():
            self._poller = asyncio.get_running_loop().create_task(self._poll(), name="foxglove-parameter-poll")

    async def unsubscribe(self, session: FoxgloveSession, names: list[str] | None) -> None:
        """Take parameters out of a client's subscription (all of them when None)."""
        mine = self.subscribers.get(session)
        if mine is None:
            return
        if names is None:
            mine.clear()
        else:
            mine.difference_update(names)
        if not mine:
            del self.subscribers[session]
        watched = self.watched()
        for name in [n for n in self.values if n not in watched]:
            del self.values[name]
        if not self.subscribers:
            await self.stop()

    def poke(self) -> None:
        """Read the subscribed parameters now (something may have changed them)."""
        self._poll_now.set()

    async def stop(self) -> None:
        """Stop polling and leave /parameter_events."""
        if self._events is not None:
            self._events.close()
            self._events = None
        poller, self._poller = self._poller, None
        if poller is not None and poller is not asyncio.current_task():
            poller.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await poller

    async def _follow_events(self) -> None:
        if self.graph.ros_version != 2 or self._events is not None:
            return
        try:
            self._events = await self.graph.subscribe(*PARAMETER_EVENTS, lambda sample: self.poke())
        except BridgeError as exc:  # polling alone still tells every change, a little later
            logger.info("foxglove: not following %s: %s", PARAMETER_EVENTS[0], exc)

    async def _poll(self) -> None:
        await self._follow_events()
        failing = False
        while self.subscribers:
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._poll_now.wait(), self.poll_s)
            self._poll_now.clear()
            watched = self.watched()
            try:
                current = await self.graph.get_params(sorted(watched))
            except Exception as exc:  # told once; the next poll tries again, and the clients keep their updates
                if not failing:
                    logger.warning("foxglove: cannot read the subscribed parameters: %s", exc)
                failing = True
                continue
            failing = False
            self.polls += 1
            changed: dict[str, dict[str, Any]] = {}
            for name in watched:
                entry = encode_parameter(name, current[name]) if name in current else {"name": name}
                if entry != self.values.get(name, {"name": name}):
                    changed[name] = entry
                    if name in current:
                        self.values[name] = entry
                    else:
                        self.values.pop(name, None)
            if changed:
                for session, names in list(self.subscribers.items()):
                    mine = [entry for name, entry in changed.items() if name in names]
                    if mine:
                        session.send({"op": "parameterValues", "parameters": mine})


class ParameterOps:
    """One client's parameter requests: getParameters, setParameters and (un)subscribeParameterUpdates."""

    def __init__(self, session: FoxgloveSession, watch: ParameterWatch) -> None:
        self.session = session
        self.graph = session.graph
        self.watch = watch

    def handlers(self) -> dict[str, Callable[[dict[str, Any]], Awaitable[None]]]:
        """Return the session's handlers of the parameter ops, by op."""
        return {
            "getParameters": self.get,
            "setParameters": self.set,
            "subscribeParameterUpdates": self.subscribe,
            "unsubscribeParameterUpdates": self.unsubscribe,
        }

    async def get(self, message: dict[str, Any]) -> None:
        """Answer the values of the parameters named (all when none are), telling which are not set."""
        names, ident = _names(message, "parameterNames"), _request_id(message)
        values = await self.graph.get_params(names)
        missing = [name for name in names or () if name not in values]
        if missing:
            self.session.status(WARNING, f"getParameters: no parameter {', '.join(missing)}"[:500])
        self._answer([encode_parameter(name, value) for name, value in values.items()], ident)

    async def set(self, message: dict[str, Any]) -> None:
        """Set parameters, all or none; answer their new values when the request has an id."""
        ident = _request_id(message)
        changes = [_decode_value(index, item) for index, item in enumerate(items_field(message, "parameters"))]
        if not changes:
            raise Fail("'parameters' is empty: name at least one")
        await set_parameters(self.graph, changes)
        self.watch.poke()
        if ident is not None:
            names = list(dict.fromkeys(name for name, _ in changes))
            values = await self.graph.get_params(names)
            self._answer([encode_parameter(n, values[n]) if n in values else {"name": n} for n in names], ident)

    async def subscribe(self, message: dict[str, Any]) -> None:
        """Send the values of these parameters whenever they change."""
        await self.watch.subscribe(self.session, _names(message, "parameterNames"))

    async def unsubscribe(self, message: dict[str, Any]) -> None:
        """Stop sending changes of these parameters (of all when none are named)."""
        await self.watch.unsubscribe(self.session, _names(message, "parameterNames"))

    def _answer(self, parameters: list[dict[str, Any]], ident: str | None) -> None:
        answer: dict[str, Any] = {"op": "parameterValues", "parameters": parameters}
        if ident is not None:
            answer["id"] = ident
        self.session.send(answer)

    async def close(self) -> None:
        """End the client's subscriptions."""
        await self.watch.unsubscribe(self.session, None)
