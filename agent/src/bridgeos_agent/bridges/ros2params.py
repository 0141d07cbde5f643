"""ROS 2 parameters for the bridges: each node's own, named ``/node_name:parameter`` as rosbridge's rosapi names them.

They are read and written through the node's parameter services (rcl_interfaces), one call per
node for any number of its parameters.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from typing import Any

from bridgeos_agent.bridges.graph import BridgeError

__all__ = ["PARAM_TIMEOUT", "Ros2Params", "from_parameter_value", "split_name", "to_parameter_value"]

PARAM_TIMEOUT = 2.0

# (service name, srv type, srv class, request, timeout) -> response: the graph's service request
Request = Callable[[str, str, Any, Any, float], Awaitable[Any]]


def split_name(name: str) -> tuple[str, str]:
    """Return (/node, parameter) of '/node:parameter'; raise BridgeError for any other spelling."""
    node, sep, parameter = name.partition(":")
    if not sep or not node.strip("/") or not parameter:
        raise BridgeError(f"ROS 2 parameters belong to nodes: name one /node_name:parameter_name, not {name!r}")
    return "/" + node.strip("/"), parameter


class Ros2Params:
    """The parameters of a ROS 2 graph's nodes, through their parameter services."""

    def __init__(self, request: Request, nodes: Callable[[], Awaitable[list[str]]]) -> None:
        self._request = request
        self._nodes = nodes

    async def _call(self, node: str, service: str, fields: dict[str, Any]) -> Any:
        from bridgeos_agent.ros2graph import interface_class

        srv_type = f"rcl_interfaces/srv/{service}"
        cls: Any = interface_class(srv_type, "srv")
        request = cls.Request()
        for key, value in fields.items():
            setattr(request, key, value)
        snake = "".join("_" + c.lower() if c.isupper() else c for c in service).lstrip("_")
        return await self._request(f"{node}/{snake}", srv_type, cls, request, PARAM_TIMEOUT)

    async def get(self, name: str) -> Any:
        """Return a node's parameter; raise KeyError when it is not set."""
        node, parameter = split_name(name)
        answer = await self._call(node, "GetParameters", {"names": [parameter]})
        if not answer.values or answer.values[0].type == 0:
            raise KeyError(name)
        return from_parameter_value(answer.values[0])

    async def values(self, names: list[str] | None) -> dict[str, Any]:
        """Return the values of the parameters named (every one when None) that are set, one call per node."""
        if names is None:
            names = await self.names()
        by_node: dict[str, list[str]] = {}
        for name in names:
            node, parameter = split_name(name)
            by_node.setdefault(node, []).append(parameter)

        async def of(node: str, parameters: list[str]) -> dict[str, Any]:
            try:
                answer = await self._call(node, "GetParameters", {"names": parameters})
            except BridgeError:  # a node that does not answer has no parameters to tell
                return {}
            if len(answer.values) != len(parameters):
                # A node that refuses the whole call for one undeclared name (rclcpp does): ask one by one.
                found = {}
                for parameter in parameters:
                    try:
                        found[f"{node}:{parameter}"] = await self.get(f"{node}:{parameter}")
                    except (KeyError, BridgeError):
                        continue
                return found
            return {
                f"{node}:{parameter}": from_parameter_value(value)
                for parameter, value in zip(parameters, answer.values, strict=True)
                if value.type != 0
            }

        found: dict[str, Any] = {}
        for part in await asyncio.gather(*(of(node, parameters) for node, parameters in by_node.items())):
            found.update(part)
        return found

    async def set(self, name: str, value: Any) -> None:
        """Set a node's parameter (the node may refuse: its reason is passed on)."""
        from rcl_interfaces.msg import Parameter

        node, parameter = split_name(name)
        answer = await self._call(
            node, "SetParameters", {"parameters": [Parameter(name=parameter, value=to_parameter_value(value))]}
        )
        result = answer.results[0]
        if not result.successful:
            raise BridgeError(f"{name}: {node} refused: {result.reason}")

    async def delete(self, name: str) -> None:
        """Undeclare a node's parameter (nodes that allow it only); raise KeyError when it is not set."""
        from rcl_interfaces.msg import Parameter, ParameterValue

        await self.get(name)
        node, parameter = split_name(name)
        answer = await self._call(
            node, "SetParameters", {"parameters": [Parameter(name=parameter, value=ParameterValue(type=0))]}
        )
        result = answer.results[0]
        if not result.successful:
            raise BridgeError(f"{name}: {node} refused to delete it: {result.reason}")

    async def names(self) -> list[str]:
        """Return '/node:parameter' for every parameter of every node that answers."""

        async def of(node: str) -> list[str]:
            try:
                answer = await self._call(node, "ListParameters", {"depth": 0})
            except BridgeError:
                return []
            return [f"{node}:{parameter}" for parameter in answer.result.names]

        nodes = [n for n in await self._nodes() if not n.endswith("_relay")]
        return [name for names in await asyncio.gather(*(of(n) for n in nodes)) for name in names]


_FIELDS = {
    1: "bool_value",
    2: "integer_value",
    3: "double_value",
    4: "string_value",
    5: "byte_array_value",
    6: "bool_array_value",
    7: "integer_array_value",
    8: "double_array_value",
    9: "string_array_value",
}


def from_parameter_value(value: Any) -> Any:
    """Return an rcl_interfaces/ParameterValue as plain data (a byte array as bytes)."""
    from bridgeos_agent.bridges.ros2graph import message_to_plain

    return message_to_plain(value)[_FIELDS[value.type]]


def to_parameter_value(value: Any) -> Any:
    """Return plain data as an rcl_interfaces/ParameterValue; raise BridgeError for what no parameter holds."""
    from rcl_interfaces.msg import ParameterValue

    if isinstance(value, bool):
        return ParameterValue(type=1, bool_value=value)
    if isinstance(value, int):
        return ParameterValue(type=2, integer_value=value)
    if isinstance(value, float):
        return ParameterValue(type=3, double_value=value)
    if isinstance(value, str):
        return ParameterValue(type=4, string_value=value)
    if isinstance(value, bytes | bytearray):
        return ParameterValue(type=5, byte_array_value=[bytes([b]) for b in value])
    if isinstance(value, list) and value:
        if all(isinstance(v, bool) for v in value):
            return ParameterValue(type=6, bool_array_value=value)
        if all(isinstance(v, int) and not isinstance(v, bool) for v in value):
            return ParameterValue(type=7, integer_array_value=value)
        if all(isinstance(v, int | float) and not isinstance(v, bool) for v in value):
            return ParameterValue(type=8, double_array_value=[float(v) for v in value])
        if all(isinstance(v, str) for v in value):
            return ParameterValue(type=9, string_array_value=value)
    raise BridgeError(
        "a ROS 2 parameter holds a boolean, an integer, a double, a string, bytes or a non-empty list of one of "
        f"them, not {value!r}"[:300]
    )
