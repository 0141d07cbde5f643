"""Proxy a Skill's ROS services to the server component's active instance, call by call."""

from __future__ import annotations

import asyncio
import functools

from bridgeos_agent.rosnames import instance_name
from bridgeos_agent.rostopics import read_header
from bridgeos_agent.router.routes import RoutedService, RouterBase
from bridgeos_agent.router.settings import Where
from bridgeos_agent.skillconfig import ServiceRoute
from bridgeos_agent.tcpros import HeaderError, encode_header

__all__ = ["ServiceRouting"]


class ServiceRouting(RouterBase):
    """Advertise each routed service under its canonical name and relay its calls."""

    def _add_service(self, route: ServiceRoute) -> None:
        assert self.node is not None
        service = RoutedService(route)
        self._services[service.canonical] = service
        self.node.advertise_service(service.canonical, functools.partial(self._serve, service))

    def _remove_service(self, canonical: str) -> None:
        self._services.pop(canonical, None)
        if self.node is not None:
            self.node.unadvertise_service(canonical)

    async def _upstream(
        self, service: RoutedService, location: Where, request: dict[str, str]
    ) -> tuple[asyncio.StreamReader, asyncio.StreamWriter, dict[str, str]]:
        """Open a connection to one instance's service and exchange headers."""
        assert self.node is not None
        name = instance_name(service.route.name, self.skill, service.route.server, location)
        where = await self.node.lookup_service(name)
        if where is None:
            raise ConnectionError(f"{service.route.server} serves no {name} on the {location}")
        reader, writer = await asyncio.wait_for(asyncio.open_connection(*where), 10)
        fields = {
            "callerid": self.node.name,
            "service": name,
            "md5sum": request.get("md5sum", "*"),
            "persistent": "1",
        }
        writer.write(encode_header(fields))
        header = await asyncio.wait_for(read_header(reader), 10)
        if "error" in header:
            writer.close()
            raise ConnectionError(header["error"])
        return reader, writer, header

    async def _serve(
        self,
        service: RoutedService,
        request: dict[str, str],
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
    ) -> None:
        """Proxy one client's calls, each to the server instance active when it arrives."""
        server = service.route.server
        location = self._active.get(server)
        if location is None:
            writer.write(encode_header({"error": f"{service.canonical}: component {server} is not running"}))
            return
        try:
            upstream = await self._upstream(service, location, request)
        except (ConnectionError, OSError, TimeoutError, HeaderError, asyncio.IncompleteReadError) as exc:
            writer.write(encode_header({"error": f"{service.canonical}: {exc}"}))
            return
        up_reader, up_writer, header = upstream
        writer.write(encode_header({**header, "callerid": self.node.name if self.node else ""}))
        try:
            while True:
                try:
                    size = int.from_bytes(await reader.readexactly(4), "little")
                    body = await reader.readexactly(size)
                except (asyncio.IncompleteReadError, ConnectionError):
                    return  # the client is done
                now_at = self._active.get(server)
                key = (server, now_at or location)
                self._enter(key)
                try:
                    if now_at != location or up_writer.is_closing():
                        up_writer.close()
                        if now_at is None:
                            raise ConnectionError(f"component {server} is not running")
                        location = now_at
                        up_reader, up_writer, _ = await self._upstream(service, location, request)
                    up_writer.write(size.to_bytes(4, "little") + body)
                    ok = await up_reader.readexactly(1)
                    length = int.from_bytes(await up_reader.readexactly(4), "little")
                    answer = await up_reader.readexactly(length)
                except (ConnectionError, OSError, TimeoutError, HeaderError, asyncio.IncompleteReadError) as exc:
                    service.errors += 1
                    message = f"{service.canonical}: {exc or type(exc).__name__}".encode()
                    writer.write(b"\x00" + len(message).to_bytes(4, "little") + message)
                    await writer.drain()
                    return
                finally:
                    self._leave(key)
                service.calls += 1
                service.bytes += size + length
                writer.write(ok + length.to_bytes(4, "little") + answer)
                await writer.drain()
        finally:
            up_writer.close()
