"""rosapi's services (``/rosapi/<name>``), answered by the bridge itself from the graph as rosbridge_suite does."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any

from bridgeos_agent.bridges.graph import BridgeError
from bridgeos_agent.bridges.rosbridgewire import json_default

if TYPE_CHECKING:
    from bridgeos_agent.bridges.rosbridge import Rosbridge

__all__ = ["ROSAPI_SERVICES", "Rosapi"]

ROSAPI_SERVICES = (
    "topics",
    "topic_type",
    "topics_for_type",
    "services",
    "service_type",
    "services_for_type",
    "nodes",
    "get_param",
    "set_param",
    "delete_param",
    "has_param",
    "get_param_names",
    "search_param",
    "get_time",
    "message_details",
    "action_servers",
)


class Rosapi:
    """rosapi's services, answered by the bridge from the graph (``/rosapi/<name>``)."""

    def __init__(self, bridge: Rosbridge) -> None:
        self.bridge = bridge
        self.graph = bridge.graph

    def names(self) -> list[str]:
        """Return the full names of the rosapi services."""
        return [f"/rosapi/{name}" for name in ROSAPI_SERVICES]

    async def call(self, name: str, args: dict[str, Any]) -> dict[str, Any]:
        """Answer one rosapi call."""
        short = name.removeprefix("/rosapi/")
        if short not in ROSAPI_SERVICES:
            raise BridgeError(f"{name} is not a rosapi service this bridge serves ({', '.join(ROSAPI_SERVICES)})")
        method: Callable[[dict[str, Any]], Awaitable[dict[str, Any]]] = getattr(self, "_" + short)
        return await method(args)

    @staticmethod
    def _arg(args: dict[str, Any], key: str, default: str | None = None) -> str:
        value = args.get(key, default)
        if not isinstance(value, str) or (default is None and not value):
            raise BridgeError(f"'{key}' must be a non-empty string")
        return value

    async def _all_services(self) -> dict[str, str]:
        services = dict(await self.graph.services())
        for name in self.names():
            services.setdefault(name, f"rosapi/{name.rsplit('/', 1)[1]}")
        return services

    async def _topics(self, args: dict[str, Any]) -> dict[str, Any]:
        topics = sorted((await self.graph.topics()).items())
        return {"topics": [t for t, _ in topics], "types": [ty for _, ty in topics]}

    async def _topic_type(self, args: dict[str, Any]) -> dict[str, Any]:
        topic = self._arg(args, "topic")
        return {"type": (await self.graph.topics()).get(topic if topic.startswith("/") else "/" + topic, "")}

    async def _topics_for_type(self, args: dict[str, Any]) -> dict[str, Any]:
        wanted = self.graph.normalize_type(self._arg(args, "type"))
        return {"topics": sorted(t for t, ty in (await self.graph.topics()).items() if ty == wanted)}

    async def _services(self, args: dict[str, Any]) -> dict[str, Any]:
        return {"services": sorted(await self._all_services())}

    async def _service_type(self, args: dict[str, Any]) -> dict[str, Any]:
        service = self._arg(args, "service")
        return {"type": (await self._all_services()).get(service if service.startswith("/") else "/" + service, "")}

    async def _services_for_type(self, args: dict[str, Any]) -> dict[str, Any]:
        wanted = self._arg(args, "type")
        return {"services": sorted(s for s, ty in (await self._all_services()).items() if ty == wanted)}

    async def _nodes(self, args: dict[str, Any]) -> dict[str, Any]:
        return {"nodes": sorted(await self.graph.nodes())}

    async def _get_param(self, args: dict[str, Any]) -> dict[str, Any]:
        name = self._arg(args, "name")
        default = args.get("default", args.get("default_value", ""))
        try:
            value = await self.graph.get_param(name)
        except KeyError:
            if default:
                return {"value": default, "successful": True, "reason": ""}
            return {"value": "null", "successful": False, "reason": f"parameter {name} is not set"}
        return {"value": json.dumps(value, default=json_default), "successful": True, "reason": ""}

    async def _set_param(self, args: dict[str, Any]) -> dict[str, Any]:
        name = self._arg(args, "name")
        text = self._arg(args, "value", "")
        try:
            value = json.loads(text)
        except ValueError:
            raise BridgeError(f"set_param {name}: 'value' must be JSON text, not {text[:64]!r}") from None
        await self.graph.set_param(name, value)
        return {"successful": True, "reason": ""}

    async def _delete_param(self, args: dict[str, Any]) -> dict[str, Any]:
        name = self._arg(args, "name")
        try:
            await self.graph.delete_param(name)
        except KeyError:
            return {"successful": False, "reason": f"parameter {name} is not set"}
        return {"successful": True, "reason": ""}

    async def _has_param(self, args: dict[str, Any]) -> dict[str, Any]:
        name = self._arg(args, "name")
        try:
            await self.graph.get_param(name)
        except KeyError:
            return {"exists": False}
        return {"exists": True}

    async def _get_param_names(self, args: dict[str, Any]) -> dict[str, Any]:
        return {"names": sorted(await self.graph.param_names())}

    async def _search_param(self, args: dict[str, Any]) -> dict[str, Any]:
        name = self._arg(args, "name")
        found = [p for p in await self.graph.param_names() if p.rstrip("/").endswith("/" + name.strip("/"))]
        return {"global_name": found[0] if found else ""}

    async def _get_time(self, args: dict[str, Any]) -> dict[str, Any]:
        secs, nsecs = self.graph.now()
        return {"time": self.graph.time_message(secs, nsecs)}

    async def _message_details(self, args: dict[str, Any]) -> dict[str, Any]:
        return {"typedefs": self.graph.message_details(self._arg(args, "type"))}

    async def _action_servers(self, args: dict[str, Any]) -> dict[str, Any]:
        return {"action_servers": sorted(await self.graph.action_servers())}
