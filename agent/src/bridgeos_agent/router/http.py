"""Proxy a Skill's HTTP routes to the serving component's active instance."""

from __future__ import annotations

import contextlib
import ipaddress
from collections.abc import Mapping

import aiohttp
from aiohttp import web

from bridgeos_agent.router.routes import RouterBase
from bridgeos_agent.skillconfig import HttpRoute

__all__ = ["HOP_HEADERS", "HttpRouting"]

# Request headers that belong to one hop, not to the request (RFC 9110 §7.6.1).
HOP_HEADERS = frozenset(
    {
        "connection",
        "keep-alive",
        "proxy-authenticate",
        "proxy-authorization",
        "te",
        "trailer",
        "transfer-encoding",
        "upgrade",
        "host",
        "content-length",
    }
)


class HttpRouting(RouterBase):
    """Serve the routes' HTTP port and forward each request to the active instance."""

    async def _start_http(self) -> None:
        self._http = sorted(self.config.router.http, key=lambda r: len(r.prefix), reverse=True)
        if self._runner is not None:
            return
        self._session = aiohttp.ClientSession(
            timeout=aiohttp.ClientTimeout(total=None, sock_connect=10), auto_decompress=False
        )
        app = web.Application(client_max_size=0)
        app.router.add_route("*", "/{tail:.*}", self._proxy)
        runner = web.AppRunner(app, access_log=None, handle_signals=False, shutdown_timeout=5.0)
        await runner.setup()
        saved = self._saved_port()
        for port in dict.fromkeys((saved, 0)):
            try:
                await web.TCPSite(runner, self.settings.http_host, port).start()
                break
            except OSError:
                if port == 0:
                    await runner.cleanup()
                    raise
        self._runner = runner
        port = runner.addresses[0][1]
        host = self.settings.http_advertise
        self.url = f"http://{f'[{host}]' if ':' in host else host}:{port}"
        if self.state_dir is not None:
            self.state_dir.mkdir(parents=True, exist_ok=True)
            (self.state_dir / f"{self.skill}.port").write_text(str(port))

    async def _stop_http(self) -> None:
        """Close the HTTP server and the client session of the proxy."""
        runner, self._runner = self._runner, None
        if runner is not None:
            await runner.cleanup()
        session, self._session = self._session, None
        if session is not None:
            await session.close()

    def _saved_port(self) -> int:
        if self.state_dir is None:
            return 0
        try:
            port = int((self.state_dir / f"{self.skill}.port").read_text())
        except (OSError, ValueError):
            return 0
        return port if 1 <= port <= 65535 else 0

    def _match(self, path: str) -> HttpRoute | None:
        for route in self._http:
            prefix = route.prefix.rstrip("/")
            if not prefix or path == prefix or path.startswith(prefix + "/"):
                return route
        return None

    def _http_target(self, route: HttpRoute, location: str) -> tuple[str, int] | None:
        component = self.config.components[route.component]
        launch = component.launch_spec(location)  # type: ignore[arg-type]
        port = route.port or (launch.ports[0] if launch is not None and launch.ports else None)
        container = self._containers.get((route.component, location))
        if container is None or not (container.get("address") or container.get("ip") or container.get("host")):
            # A robot instance listens on the robot itself unless its runtime reported an address.
            return ("127.0.0.1", port) if location == "robot" and port else None
        host = container.get("address") or container.get("ip") or container.get("host")
        ports = container.get("ports")
        if isinstance(ports, Mapping):
            published = ports.get(str(port)) if port else next(iter(ports.values()), None)
        else:
            published = port
        if not host or not published:
            return None
        try:
            return str(host), int(published)
        except (TypeError, ValueError):
            return None

    async def _http_answers(self, route: HttpRoute, location: str) -> bool:
        target = self._http_target(route, location)
        if target is None or self._session is None:
            return False
        host, port = target
        url = f"http://{_url_host(host)}:{port}{route.prefix}"
        try:
            async with self._session.get(url, timeout=aiohttp.ClientTimeout(total=2)) as response:
                return response.status < 500
        except (aiohttp.ClientError, OSError, TimeoutError):
            return False

    async def _proxy(self, request: web.Request) -> web.StreamResponse:
        route = self._match(request.path)
        if route is None:
            return web.json_response({"error": f"no route for {request.path}"}, status=404)
        if request.method not in route.methods:
            return web.json_response(
                {"error": f"{request.method} is not routed on {route.prefix}"},
                status=405,
                headers={"Allow": ", ".join(route.methods)},
            )
        component = route.component
        location = self._active.get(component)
        target = self._http_target(route, location) if location else None
        counts = self._http_counts.setdefault(component, [0, 0, 0])
        if location is None or target is None or self._session is None:
            counts[2] += 1
            reason = "is not running" if location is None else f"has no known address on the {location}"
            return web.json_response({"error": f"component {component} {reason}"}, status=503)
        key = (component, location)
        self._enter(key)
        try:
            return await self._forward(request, target, counts)
        finally:
            self._leave(key)

    async def _forward(self, request: web.Request, target: tuple[str, int], counts: list[int]) -> web.StreamResponse:
        assert self._session is not None
        host, port = target
        url = f"http://{_url_host(host)}:{port}{request.rel_url}"
        headers = {k: v for k, v in request.headers.items() if k.lower() not in HOP_HEADERS}
        headers["X-Forwarded-For"] = request.remote or ""
        data = request.content if request.body_exists else None
        try:
            async with self._session.request(
                request.method, url, headers=headers, data=data, allow_redirects=False
            ) as upstream:
                response = web.StreamResponse(status=upstream.status, reason=upstream.reason)
                for key, value in upstream.headers.items():
                    if key.lower() not in HOP_HEADERS:
                        response.headers.add(key, value)
                if upstream.content_length is not None:
                    response.content_length = upstream.content_length
                await response.prepare(request)
                sent = 0
                async for chunk in upstream.content.iter_any():
                    sent += len(chunk)
                    await response.write(chunk)
                await response.write_eof()
        except (aiohttp.ClientError, OSError, TimeoutError) as exc:
            counts[2] += 1
            return web.json_response({"error": f"the component did not answer: {exc}"}, status=502)
        counts[0] += 1
        counts[1] += sent + (request.content_length or 0)
        return response


def _url_host(host: str) -> str:
    with contextlib.suppress(ValueError):
        if ipaddress.ip_address(host).version == 6:
            return f"[{host}]"
    return host
