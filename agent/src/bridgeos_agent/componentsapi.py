"""Serve the Components API (thesis Table 3.2): one small HTTP server per Skill, run by its manager.

Components reach it through ``BRIDGEOS_MANAGER_URL`` to read their Skill's components and
metrics, publish custom metrics and push manual offloading recommendations. The server owns
no state: it validates requests and hands them to the manager through :class:`SkillView`.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Collection, Iterable
from typing import Annotated, Any, NotRequired, Protocol

from aiohttp import web
from pydantic import Field, TypeAdapter, ValidationError, with_config

# pydantic needs typing_extensions' TypedDict before Python 3.12; pydantic itself depends on it.
from typing_extensions import TypedDict

from bridgeos_agent.protocol import (
    MAX_FRAME_BYTES,
    MAX_HOLD_S,
    MAX_METRICS_PER_FRAME,
    FiniteFloat,
    LabelKey,
    LabelValue,
    MetricName,
    Slug,
    Timestamp,
)

__all__ = ["MAX_BODY_BYTES", "ComponentsAPI", "MetricStore", "SkillView"]

MAX_BODY_BYTES = MAX_FRAME_BYTES
MOVABLE = "either"
TARGETS = frozenset({"robot", "cloud"})


class SkillView(Protocol):
    """What the Components API needs from its Skill's manager."""

    def components(self) -> list[dict[str, Any]]:
        """Describe every component: id, name, location, active_location, status."""
        ...

    def component(self, component_id: str) -> dict[str, Any]:
        """Describe one component; raise KeyError if the Skill has no such component."""
        ...

    def locations(self) -> dict[str, str | None]:
        """Map every component id to its active location (None while not running)."""
        ...

    def recommend(self, component_id: str, location: str) -> None:
        """Queue a manual offloading recommendation; raise ValueError saying why if refused."""
        ...

    def hold(self, component_id: str, seconds: float, reason: str) -> None:
        """Hold the robot's updates for ``seconds`` at most on a component's behalf (0 releases its hold)."""
        ...

    def latest_metrics(self, names: Collection[str] | None, component: str | None) -> list[dict[str, Any]]:
        """Return the latest point of each (name, component), optionally filtered."""
        ...

    def publish(self, points: list[dict[str, Any]]) -> int:
        """Record validated metric points; return how many were applied."""
        ...


class MetricStore:
    """Keep the latest point per (metric name, component), forgetting the least recently updated."""

    def __init__(self, max_entries: int = 10_000) -> None:
        if max_entries < 1:
            raise ValueError("max_entries must be at least 1")
        self.max_entries = max_entries
        # Insertion order doubles as recency order: an update moves its key to the end.
        self._latest: dict[tuple[str, str | None], dict[str, Any]] = {}
        self._by_name: dict[str, dict[str | None, dict[str, Any]]] = {}

    def __len__(self) -> int:
        return len(self._latest)

    def publish(self, points: list[dict[str, Any]]) -> int:
        """Store each point unless an equally new or newer one is already held; return how many were stored."""
        latest, by_name = self._latest, self._by_name
        stored = 0
        for point in points:
            name = point["name"]
            component = point.get("component")
            key = (name, component)
            held = latest.pop(key, None)
            if held is not None and held["ts"] > point["ts"]:
                latest[key] = held
                continue
            latest[key] = point
            by_name.setdefault(name, {})[component] = point
            stored += 1
            if len(latest) > self.max_entries:
                self._evict_oldest()
        return stored

    def latest(self, names: Collection[str] | None = None, component: str | None = None) -> list[dict[str, Any]]:
        """Return the latest points, only of ``names`` and ``component`` when given."""
        by_name = self._by_name
        groups: Iterable[dict[str | None, dict[str, Any]]]
        if names is None:
            groups = by_name.values()
        else:
            groups = [by_name[name] for name in names if name in by_name]
        if component is None:
            return [point for group in groups for point in group.values()]
        return [group[component] for group in groups if component in group]

    def _evict_oldest(self) -> None:
        name, component = key = next(iter(self._latest))
        del self._latest[key]
        group = self._by_name[name]
        del group[component]
        if not group:
            del self._by_name[name]


# --------------------------------------------------------------------------- validation

# The same field rules as protocol.MetricPoint, as TypedDicts so validation yields plain dicts.
Labels = Annotated[dict[LabelKey, LabelValue], Field(max_length=16)]


@with_config(extra="forbid")
class _Sample(TypedDict):
    value: FiniteFloat
    ts: NotRequired[Timestamp]
    component: NotRequired[Slug]
    labels: NotRequired[Labels]


@with_config(extra="forbid")
class _Point(_Sample):
    name: MetricName


@with_config(extra="forbid")
class _Batch(TypedDict):
    metrics: Annotated[list[_Point], Field(max_length=MAX_METRICS_PER_FRAME)]


@with_config(extra="forbid")
class _Recommendation(TypedDict):
    location: str


@with_config(extra="forbid")
class _Hold(TypedDict):
    seconds: Annotated[float, Field(gt=0, le=MAX_HOLD_S, allow_inf_nan=False)]
    reason: NotRequired[Annotated[str, Field(max_length=500)]]


_BATCH = TypeAdapter(_Batch)
_SAMPLE = TypeAdapter(_Sample)
_RECOMMENDATION = TypeAdapter(_Recommendation)
_HOLD = TypeAdapter(_Hold)
_NAME = TypeAdapter(MetricName)


class _Refusal(Exception):
    """Answer the request with a JSON error and change nothing."""

    def __init__(self, status: int, message: str, field: str | None = None) -> None:
        super().__init__(message)
        self.status = status
        self.message = message
        self.field = field


def _error(status: int, message: str, field: str | None) -> web.Response:
    return web.json_response({"error": message, "field": field}, status=status)


def _validate(adapter: TypeAdapter[Any], data: Any) -> Any:
    try:
        return adapter.validate_python(data)
    except ValidationError as exc:
        first = exc.errors(include_url=False, include_context=False, include_input=False)[0]
        field = ".".join(str(part) for part in first["loc"]) or None
        raise _Refusal(400, f"{first['msg']} ({exc.error_count()} error(s))", field) from None


def _reject_non_finite(token: str) -> float:
    raise ValueError(f"{token} is not valid JSON")


@web.middleware
async def _json_errors(request: web.Request, handler: Callable[..., Any]) -> web.StreamResponse:
    """Turn every refusal, including aiohttp's own 404/405/413, into a JSON error."""
    try:
        return await handler(request)
    except _Refusal as exc:
        return _error(exc.status, exc.message, exc.field)
    except web.HTTPException as exc:
        if exc.status < 400:
            raise
        if exc.status == 404:
            return _error(404, f"no route {request.path}", None)
        if exc.status == 405:
            return _error(405, f"{request.method} is not allowed on {request.path}", None)
        return _error(exc.status, exc.reason, None)


class ComponentsAPI:
    """Serve thesis Table 3.2 over HTTP for one Skill, on ``host:port`` (port 0 picks a free one)."""

    def __init__(
        self,
        view: SkillView,
        host: str = "127.0.0.1",
        port: int = 0,
        *,
        max_body: int = MAX_BODY_BYTES,
        clock: Callable[[], float] = time.time,
    ) -> None:
        self.view = view
        self.host = host
        self.port = port
        self.max_body = max_body
        self.clock = clock
        self.base_url: str | None = None
        self._runner: web.AppRunner | None = None

    def make_app(self) -> web.Application:
        """Build the aiohttp application with every route of Table 3.2."""
        app = web.Application(middlewares=[_json_errors], client_max_size=self.max_body)
        # /components/location is registered before /components/{id} so it is not read as an id.
        app.router.add_get("/components", self._components)
        app.router.add_get("/components/location", self._locations)
        app.router.add_get("/components/{id}", self._component)
        app.router.add_get("/components/{id}/location", self._component_location)
        app.router.add_post("/components/{id}/location", self._recommend)
        # A busy component defers its robot's updates (a rollout installs once released or past the deadline).
        app.router.add_post("/components/{id}/hold", self._hold)
        app.router.add_delete("/components/{id}/hold", self._release)
        app.router.add_get("/metrics", self._metrics)
        app.router.add_post("/metrics", self._publish_many)
        app.router.add_get("/metrics/{metric}", self._metric)
        app.router.add_post("/metrics/{metric}", self._publish_one)
        return app

    async def start(self) -> str:
        """Start listening and return the base URL components should use."""
        if self._runner is not None:
            raise RuntimeError("the Components API is already running")
        runner = web.AppRunner(self.make_app(), access_log=None, handle_signals=False)
        await runner.setup()
        try:
            await web.TCPSite(runner, self.host, self.port).start()
        except BaseException:
            await runner.cleanup()
            raise
        self._runner = runner
        host, port = runner.addresses[0][:2]
        self.port = port
        self.base_url = f"http://{f'[{host}]' if ':' in host else host}:{port}"
        return self.base_url

    async def stop(self) -> None:
        """Stop listening and close open connections."""
        runner, self._runner = self._runner, None
        if runner is not None:
            await runner.cleanup()

    # ----------------------------------------------------------------------- components

    async def _components(self, request: web.Request) -> web.Response:
        return web.json_response({"components": self.view.components()})

    async def _locations(self, request: web.Request) -> web.Response:
        return web.json_response({"locations": self.view.locations()})

    async def _component(self, request: web.Request) -> web.Response:
        return web.json_response(self._find(request.match_info["id"]))

    async def _component_location(self, request: web.Request) -> web.Response:
        component = self._find(request.match_info["id"])
        return web.json_response({"id": component["id"], "location": component["active_location"]})

    async def _recommend(self, request: web.Request) -> web.Response:
        body = _validate(_RECOMMENDATION, await self._read_json(request))
        component = self._find(request.match_info["id"])
        location = body["location"]
        if location not in TARGETS:
            raise _Refusal(400, "location must be 'robot' or 'cloud'", "location")
        if component["location"] != MOVABLE:
            raise _Refusal(409, f"component {component['id']!r} is pinned to the {component['location']}", "location")
        try:
            self.view.recommend(component["id"], location)
        except ValueError as exc:
            raise _Refusal(409, str(exc), "location") from None
        return web.json_response({"id": component["id"], "location": location}, status=202)

    async def _hold(self, request: web.Request) -> web.Response:
        body = _validate(_HOLD, await self._read_json(request))
        component = self._find(request.match_info["id"])
        self.view.hold(component["id"], body["seconds"], body.get("reason", ""))
        return web.json_response({"id": component["id"], "seconds": body["seconds"]}, status=202)

    async def _release(self, request: web.Request) -> web.Response:
        component = self._find(request.match_info["id"])
        self.view.hold(component["id"], 0, "")
        return web.json_response({"id": component["id"], "seconds": 0}, status=202)

    def _find(self, component_id: str) -> dict[str, Any]:
        try:
            return self.view.component(component_id)
        except KeyError:
            raise _Refusal(404, f"unknown component {component_id!r}", "id") from None

    # ----------------------------------------------------------------------- metrics

    async def _metrics(self, request: web.Request) -> web.Response:
        query = request.query
        names = None
        if "names" in query:
            names = [name for name in query["names"].split(",") if name]
            for name in names:
                _validate_name(name, "names")
        component = self._query_component(request)
        return web.json_response({"metrics": self.view.latest_metrics(names, component)})

    async def _metric(self, request: web.Request) -> web.Response:
        name = _validate_name(request.match_info["metric"], "metric")
        points = self.view.latest_metrics((name,), self._query_component(request))
        if not points:
            raise _Refusal(404, f"no value of metric {name!r}", "metric")
        return web.json_response({"metrics": points})

    async def _publish_many(self, request: web.Request) -> web.Response:
        points = _validate(_BATCH, await self._read_json(request))["metrics"]
        self._check_components(points, "metrics.{}.component")
        return web.json_response({"accepted": self.view.publish(points)})

    async def _publish_one(self, request: web.Request) -> web.Response:
        name = _validate_name(request.match_info["metric"], "metric")
        point = _validate(_SAMPLE, await self._read_json(request))
        point["name"] = name
        self._check_components((point,), "component")
        return web.json_response({"accepted": self.view.publish([point])})

    def _query_component(self, request: web.Request) -> str | None:
        component = request.query.get("component")
        if component is not None and component not in self.view.locations():
            raise _Refusal(404, f"unknown component {component!r}", "component")
        return component

    def _check_components(self, points: Collection[dict[str, Any]], field: str) -> None:
        """Reject points about unknown components, and stamp the ones without a timestamp."""
        known = None
        now = None
        for index, point in enumerate(points):
            component = point.get("component")
            if component is not None:
                if known is None:
                    known = self.view.locations()
                if component not in known:
                    raise _Refusal(400, f"unknown component {component!r}", field.format(index))
            if "ts" not in point:
                if now is None:
                    now = self.clock()
                point["ts"] = now

    async def _read_json(self, request: web.Request) -> Any:
        if request.content_length is not None and request.content_length > self.max_body:
            raise _Refusal(413, f"body larger than {self.max_body} bytes", None)
        if request.content_type != "application/json":
            raise _Refusal(415, "send the body as application/json", None)
        raw = await request.read()
        try:
            return json.loads(raw, parse_constant=_reject_non_finite)
        except ValueError as exc:
            raise _Refusal(400, f"body is not valid JSON: {exc}", None) from None


def _validate_name(name: str, field: str) -> str:
    try:
        return _NAME.validate_python(name)
    except ValidationError:
        raise _Refusal(400, f"invalid metric name {name!r}", field) from None
