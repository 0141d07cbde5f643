"""Test the Components API (thesis Table 3.2) over real sockets, and with a real component process."""

from __future__ import annotations

import asyncio
import json
import os
import sys
import textwrap
from collections.abc import AsyncIterator, Collection
from importlib import resources
from typing import Any

import httpx
import pydantic
import pytest

from bridgeos_agent.componentsapi import ComponentsAPI, MetricStore, SkillView
from bridgeos_agent.protocol import MetricPoint
from bridgeos_agent.skillconfig import SkillConfig, parse_skill_config

NOW = 1_700_000_000.0


class DemoSkill:
    """Stand in for a Skill's manager: a real Skill config and a real MetricStore."""

    def __init__(self, config: SkillConfig) -> None:
        self.config = config
        self.store = MetricStore()
        self.active = {
            cid: ("cloud" if component.location == "cloud" else "robot") for cid, component in config.components.items()
        }
        self.recommendations: list[tuple[str, str]] = []

    def components(self) -> list[dict[str, Any]]:
        return [self.component(cid) for cid in self.config.components]

    def component(self, component_id: str) -> dict[str, Any]:
        component = self.config.components[component_id]
        return {
            "id": component_id,
            "name": component.name,
            "location": str(component.location),
            "active_location": self.active[component_id],
            "status": "running",
        }

    def locations(self) -> dict[str, str | None]:
        return dict(self.active)

    def recommend(self, component_id: str, location: str) -> None:
        if self.active[component_id] == location:
            raise ValueError(f"component {component_id!r} already runs in the {location}")
        self.recommendations.append((component_id, location))

    def latest_metrics(self, names: Collection[str] | None, component: str | None) -> list[dict[str, Any]]:
        return self.store.latest(names, component)

    def publish(self, points: list[dict[str, Any]]) -> int:
        return self.store.publish(points)


def _demo_config() -> SkillConfig:
    sample = resources.files("bridgeos_agent").joinpath("samples").joinpath("demo_telemetry.json")
    return parse_skill_config(sample.read_text())


@pytest.fixture
def skill() -> DemoSkill:
    return DemoSkill(_demo_config())


@pytest.fixture
async def api(skill: DemoSkill) -> AsyncIterator[ComponentsAPI]:
    server = ComponentsAPI(skill, clock=lambda: NOW)
    await server.start()
    yield server
    await server.stop()


@pytest.fixture
async def client(api: ComponentsAPI) -> AsyncIterator[httpx.AsyncClient]:
    async with httpx.AsyncClient(base_url=api.base_url, timeout=5) as http:
        yield http


def test_demo_skill_satisfies_the_skill_view_protocol(skill: DemoSkill) -> None:
    view: SkillView = skill
    assert view.locations()


# --------------------------------------------------------------------------- server lifecycle


async def test_start_binds_an_ephemeral_loopback_port_and_stop_frees_it(skill: DemoSkill) -> None:
    server = ComponentsAPI(skill)
    base_url = await server.start()
    assert base_url.startswith("http://127.0.0.1:")
    assert server.port > 0
    async with httpx.AsyncClient() as http:
        assert (await http.get(f"{base_url}/components")).status_code == 200
        await server.stop()
        with pytest.raises(httpx.ConnectError):
            await http.get(f"{base_url}/components")


async def test_starting_twice_is_refused(api: ComponentsAPI) -> None:
    with pytest.raises(RuntimeError):
        await api.start()


# --------------------------------------------------------------------------- components


async def test_components_lists_every_component_of_the_skill(client: httpx.AsyncClient) -> None:
    response = await client.get("/components")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("application/json")
    by_id = {component["id"]: component for component in response.json()["components"]}
    assert set(by_id) == {"sensor", "filter", "planner"}
    assert by_id["sensor"] == {
        "id": "sensor",
        "name": "Sensor reader",
        "location": "robot",
        "active_location": "robot",
        "status": "running",
    }
    assert by_id["filter"]["location"] == "either"


async def test_components_location_maps_each_component_to_its_active_location(
    client: httpx.AsyncClient, skill: DemoSkill
) -> None:
    skill.active["planner"] = "cloud"
    response = await client.get("/components/location")
    assert response.json() == {"locations": {"sensor": "robot", "filter": "robot", "planner": "cloud"}}


async def test_one_component_and_its_location_are_served(client: httpx.AsyncClient) -> None:
    response = await client.get("/components/filter")
    assert response.status_code == 200
    assert response.json()["name"] == "Filter"
    response = await client.get("/components/filter/location")
    assert response.json() == {"id": "filter", "location": "robot"}


@pytest.mark.parametrize("path", ["/components/ghost", "/components/ghost/location"])
async def test_unknown_component_is_404(client: httpx.AsyncClient, path: str) -> None:
    response = await client.get(path)
    assert response.status_code == 404
    assert response.json() == {"error": "unknown component 'ghost'", "field": "id"}


async def test_recommendation_for_a_movable_component_is_accepted(client: httpx.AsyncClient, skill: DemoSkill) -> None:
    response = await client.post("/components/planner/location", json={"location": "cloud"})
    assert response.status_code == 202
    assert response.json() == {"id": "planner", "location": "cloud"}
    assert skill.recommendations == [("planner", "cloud")]


@pytest.mark.parametrize(
    ("path", "body", "status", "field"),
    [
        ("/components/sensor/location", {"location": "cloud"}, 409, "location"),
        ("/components/planner/location", {"location": "robot"}, 409, "location"),
        ("/components/planner/location", {"location": "either"}, 400, "location"),
        ("/components/planner/location", {"location": "moon"}, 400, "location"),
        ("/components/planner/location", {"location": 1}, 400, "location"),
        ("/components/planner/location", {}, 400, "location"),
        ("/components/planner/location", {"location": "cloud", "now": True}, 400, "now"),
        ("/components/planner/location", ["cloud"], 400, None),
        ("/components/ghost/location", {"location": "cloud"}, 404, "id"),
    ],
)
async def test_refused_recommendation_changes_nothing(
    client: httpx.AsyncClient, skill: DemoSkill, path: str, body: Any, status: int, field: str | None
) -> None:
    response = await client.post(path, json=body)
    assert response.status_code == status
    assert response.json()["field"] == field
    assert response.json()["error"]
    assert skill.recommendations == []


# --------------------------------------------------------------------------- metrics


async def test_published_metrics_are_served_latest_first(client: httpx.AsyncClient, skill: DemoSkill) -> None:
    response = await client.post(
        "/metrics",
        json={
            "metrics": [
                {"name": "fps", "value": 10, "ts": 5.0, "component": "sensor"},
                {"name": "fps", "value": 12.5, "ts": 6.0, "component": "sensor"},
                {"name": "fps", "value": 3, "component": "filter", "labels": {"camera": "front"}},
                {"name": "battery", "value": 0.8},
            ]
        },
    )
    assert response.status_code == 200
    assert response.json() == {"accepted": 4}
    assert len(skill.store) == 3

    everything = (await client.get("/metrics")).json()["metrics"]
    assert {(p["name"], p.get("component"), p["value"]) for p in everything} == {
        ("fps", "sensor", 12.5),
        ("fps", "filter", 3),
        ("battery", None, 0.8),
    }
    filtered = (await client.get("/metrics", params={"names": "fps,battery", "component": "filter"})).json()
    assert filtered == {
        "metrics": [{"name": "fps", "value": 3, "component": "filter", "labels": {"camera": "front"}, "ts": NOW}]
    }
    assert (await client.get("/metrics", params={"names": "nothing"})).json() == {"metrics": []}


async def test_one_metric_is_served_per_component(client: httpx.AsyncClient) -> None:
    await client.post("/metrics/cpu.load", json={"value": 0.5, "component": "sensor", "ts": 1.0})
    await client.post("/metrics/cpu.load", json={"value": 0.7, "component": "planner"})
    response = await client.get("/metrics/cpu.load")
    assert response.status_code == 200
    assert {p["component"]: p["value"] for p in response.json()["metrics"]} == {"sensor": 0.5, "planner": 0.7}
    only = (await client.get("/metrics/cpu.load", params={"component": "planner"})).json()
    assert only == {"metrics": [{"name": "cpu.load", "value": 0.7, "component": "planner", "ts": NOW}]}


async def test_posting_one_metric_answers_how_many_were_applied(client: httpx.AsyncClient) -> None:
    assert (await client.post("/metrics/temp", json={"value": 40.0, "ts": 9.0})).json() == {"accepted": 1}
    # An older point never replaces a newer one.
    assert (await client.post("/metrics/temp", json={"value": 20.0, "ts": 8.0})).json() == {"accepted": 0}
    assert (await client.get("/metrics/temp")).json()["metrics"][0]["value"] == 40.0


@pytest.mark.parametrize(
    ("path", "status", "field"),
    [
        ("/metrics/never-published", 404, "metric"),
        ("/metrics/9bad", 400, "metric"),
        ("/metrics?names=ok,9bad", 400, "names"),
        ("/metrics?component=ghost", 404, "component"),
        ("/metrics/fps?component=ghost", 404, "component"),
    ],
)
async def test_bad_metric_queries_are_refused(client: httpx.AsyncClient, path: str, status: int, field: str) -> None:
    response = await client.get(path)
    assert response.status_code == status
    assert response.json()["field"] == field


BAD_POINTS = [
    ({"name": "9starts-with-digit", "value": 1}, "metrics.1.name"),
    ({"name": "has space", "value": 1}, "metrics.1.name"),
    ({"name": "x" * 129, "value": 1}, "metrics.1.name"),
    ({"name": "fps", "value": "1.5"}, "metrics.1.value"),
    ({"name": "fps", "value": True}, "metrics.1.value"),
    ({"name": "fps", "value": 1e400}, "metrics.1.value"),
    ({"name": "fps"}, "metrics.1.value"),
    ({"name": "fps", "value": 1, "ts": -1}, "metrics.1.ts"),
    ({"name": "fps", "value": 1, "component": "Not A Slug"}, "metrics.1.component"),
    ({"name": "fps", "value": 1, "labels": {f"k{i}": "v" for i in range(17)}}, "metrics.1.labels"),
    ({"name": "fps", "value": 1, "labels": {"k": 1}}, "metrics.1.labels.k"),
    ({"name": "fps", "value": 1, "unit": "Hz"}, "metrics.1.unit"),
]


@pytest.mark.parametrize(("point", "field"), BAD_POINTS)
async def test_invalid_point_rejects_the_whole_batch(
    client: httpx.AsyncClient, skill: DemoSkill, point: dict[str, Any], field: str
) -> None:
    good = {"name": "fps", "value": 1}
    # 1e400 must reach the server as a literal, which json.dumps cannot write.
    body = json.dumps({"metrics": [good, point]}).replace("Infinity", "1e400")
    response = await client.post("/metrics", content=body, headers={"content-type": "application/json"})
    assert response.status_code == 400
    assert response.json()["field"] == field
    assert len(skill.store) == 0


@pytest.mark.parametrize(("point", "field"), [p for p in BAD_POINTS if not p[1].endswith("unit")])
def test_invalid_points_are_invalid_metric_points_too(point: dict[str, Any], field: str) -> None:
    with pytest.raises(pydantic.ValidationError):
        pydantic.TypeAdapter(MetricPoint).validate_python({"ts": 1.0, **point})


async def test_points_about_unknown_components_are_refused(client: httpx.AsyncClient, skill: DemoSkill) -> None:
    body = {"metrics": [{"name": "fps", "value": 1}, {"name": "fps", "value": 1, "component": "ghost"}]}
    response = await client.post("/metrics", json=body)
    assert (response.status_code, response.json()["field"]) == (400, "metrics.1.component")
    response = await client.post("/metrics/fps", json={"value": 1, "component": "ghost"})
    assert (response.status_code, response.json()["field"]) == (400, "component")
    assert len(skill.store) == 0


async def test_a_batch_over_the_point_limit_is_refused(client: httpx.AsyncClient, skill: DemoSkill) -> None:
    response = await client.post("/metrics", json={"metrics": [{"name": "m", "value": 1}] * 10_001})
    assert (response.status_code, response.json()["field"]) == (400, "metrics")
    assert len(skill.store) == 0


# --------------------------------------------------------------------------- HTTP errors


async def test_malformed_json_is_400(client: httpx.AsyncClient) -> None:
    for body in (b"{", b"", b'{"metrics": [{"name": "fps", "value": NaN}]}'):
        response = await client.post("/metrics", content=body, headers={"content-type": "application/json"})
        assert response.status_code == 400
        assert response.json()["error"].startswith("body is not valid JSON")


async def test_a_body_that_is_not_json_is_415(client: httpx.AsyncClient) -> None:
    response = await client.post("/metrics/fps", content=b"value=1", headers={"content-type": "text/plain"})
    assert response.status_code == 415
    assert response.json() == {"error": "send the body as application/json", "field": None}


async def test_an_oversized_body_is_413(client: httpx.AsyncClient, skill: DemoSkill) -> None:
    body = b'{"metrics": [' + b" " * (1 << 20) + b"]}"
    response = await client.post("/metrics", content=body, headers={"content-type": "application/json"})
    assert response.status_code == 413
    assert "error" in response.json()


async def test_an_oversized_chunked_body_is_413(client: httpx.AsyncClient) -> None:
    async def chunks() -> AsyncIterator[bytes]:
        yield b'{"metrics": ['
        for _ in range(20):
            yield b" " * 65536
        yield b"]}"

    response = await client.post("/metrics", content=chunks(), headers={"content-type": "application/json"})
    assert response.status_code == 413
    assert "error" in response.json()


async def test_unknown_route_is_404_json(client: httpx.AsyncClient) -> None:
    response = await client.get("/robots")
    assert response.status_code == 404
    assert response.json() == {"error": "no route /robots", "field": None}


@pytest.mark.parametrize(("method", "path"), [("DELETE", "/metrics"), ("POST", "/components"), ("PUT", "/metrics/x")])
async def test_wrong_method_is_405_json(client: httpx.AsyncClient, method: str, path: str) -> None:
    response = await client.request(method, path)
    assert response.status_code == 405
    assert response.json()["error"] == f"{method} is not allowed on {path}"


# --------------------------------------------------------------------------- MetricStore


def test_store_forgets_the_least_recently_updated_point_when_full() -> None:
    store = MetricStore(max_entries=2)
    store.publish([{"name": "a", "value": 1.0, "ts": 1.0}, {"name": "b", "value": 1.0, "ts": 1.0}])
    store.publish([{"name": "a", "value": 2.0, "ts": 2.0}])
    store.publish([{"name": "c", "value": 1.0, "ts": 1.0, "component": "x"}])
    assert len(store) == 2
    assert {(p["name"], p["value"]) for p in store.latest()} == {("a", 2.0), ("c", 1.0)}
    assert store.latest(["b"]) == []
    assert store.latest(component="x") == [{"name": "c", "value": 1.0, "ts": 1.0, "component": "x"}]


def test_store_needs_room_for_one_point() -> None:
    with pytest.raises(ValueError):
        MetricStore(max_entries=0)


# --------------------------------------------------------------------------- contract

COMPONENT = textwrap.dedent(
    """
    import json, os, urllib.request

    base = os.environ["BRIDGEOS_MANAGER_URL"]

    def call(method, path, body=None):
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(base + path, data=data, method=method)
        if data is not None:
            request.add_header("Content-Type", "application/json")
        with urllib.request.urlopen(request, timeout=5) as response:
            return response.status, json.load(response)

    status, listing = call("GET", "/components")
    ids = sorted(component["id"] for component in listing["components"])
    published = call("POST", "/metrics", {"metrics": [
        {"name": "detections", "value": len(ids), "component": "filter", "labels": {"model": "yolo"}}
    ]})
    recommended = call("POST", "/components/filter/location", {"location": "cloud"})
    print(json.dumps({"ids": ids, "published": published, "recommended": recommended}))
    """
)


async def test_a_real_component_process_uses_the_components_api(api: ComponentsAPI, skill: DemoSkill) -> None:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        COMPONENT,
        env={**os.environ, "BRIDGEOS_MANAGER_URL": api.base_url or ""},
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    stdout, stderr = await asyncio.wait_for(process.communicate(), timeout=10)
    assert process.returncode == 0, stderr.decode()
    seen = json.loads(stdout)
    assert seen == {
        "ids": ["filter", "planner", "sensor"],
        "published": [200, {"accepted": 1}],
        "recommended": [202, {"id": "filter", "location": "cloud"}],
    }
    assert skill.store.latest(["detections"], "filter") == [
        {"name": "detections", "value": 3, "component": "filter", "labels": {"model": "yolo"}, "ts": NOW}
    ]
    assert skill.recommendations == [("filter", "cloud")]
