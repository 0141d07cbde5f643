"""A ROS 1 node on asyncio: master and slave XML-RPC, TCPROS topics and services, bytes unparsed.

The Skill Router speaks ROS itself instead of importing rospy: rospy allows one node per
process, costs ~35 MB and cannot be imported by the agent's own interpreter. This node
does what a router needs and no more: it registers publications, subscriptions and
services with the master (batched in ``system.multicall`` requests), answers the slave API
(``requestTopic``, ``publisherUpdate``, ``getBusInfo``, ``getPid``...), accepts TCPROS
subscribers and service clients, connects to publishers, and hands each burst of message
frames on as one ``bytes`` without decoding a message. The topic connections themselves
(publications, subscriptions, their TCPROS framing) live in ``rostopics``; their names are
re-exported here.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import os
import xmlrpc.client
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any
from urllib.parse import urlsplit

import aiohttp
from aiohttp import web

from bridgeos_agent.rostopics import (
    Inbound,
    MessageCallback,
    Outbound,
    Publication,
    Subscription,
    iter_frames,
    nodelay,
    read_header,
)
from bridgeos_agent.tcpros import HeaderError, encode_header

__all__ = [
    "Inbound",
    "MasterError",
    "Outbound",
    "Publication",
    "RosNode",
    "Subscription",
    "iter_frames",
    "read_header",
]

logger = logging.getLogger(__name__)

BATCH = 500  # master calls per system.multicall request
ServiceHandler = Callable[[dict[str, str], asyncio.StreamReader, asyncio.StreamWriter], Awaitable[None]]


class MasterError(RuntimeError):
    """The ROS master refused a call or could not be reached."""


class RosNode:
    """One ROS 1 node on the running event loop, with batched master registrations."""

    def __init__(
        self,
        name: str,
        master_uri: str,
        *,
        host: str = "127.0.0.1",
        on_publisher_header: Callable[[Subscription, Inbound], None] | None = None,
    ) -> None:
        self.name = name
        self.master_uri = master_uri
        self.host = host
        self.uri = ""
        self.tcpros_port = 0
        self.publications: dict[str, Publication] = {}
        self.subscriptions: dict[str, Subscription] = {}
        self.services: dict[str, ServiceHandler] = {}
        self._header_hook = on_publisher_header
        self._session: aiohttp.ClientSession | None = None
        self._runner: web.AppRunner | None = None
        self._server: asyncio.Server | None = None
        self._pending: list[tuple[str, tuple[Any, ...]]] = []
        self._errors: list[MasterError] = []
        self._wake = asyncio.Event()
        self._idle = asyncio.Event()
        self._idle.set()
        self._tasks: set[asyncio.Task] = set()
        self._registrar: asyncio.Task | None = None
        self._ids = itertools.count(1)

    # ------------------------------------------------------------------ life cycle

    async def start(self) -> None:
        """Serve the slave API and TCPROS, and check the master answers."""
        # One listening socket: bound to every family at once (None), IPv4 and IPv6 each get a port of
        # their own, and the advertised URI could name the IPv6 one (the master's publisherUpdate was
        # then refused and the node heard nothing, seen with ROS_IP on a non-loopback address).
        if self.host in ("127.0.0.1", "localhost", "::1"):
            bind = "127.0.0.1"
        else:
            bind = "::" if ":" in self.host else "0.0.0.0"
        self._session = aiohttp.ClientSession(
            connector=aiohttp.TCPConnector(limit=64), timeout=aiohttp.ClientTimeout(total=30)
        )
        try:
            # A master that is not there should cost a Skill seconds, not the 30 s of a registration.
            await asyncio.wait_for(self.master_call("getPid"), 5)
            app = web.Application(client_max_size=16 << 20)
            app.router.add_post("/{tail:.*}", self._slave_request)
            # A master keeps its slave connections alive: do not wait for it to hang up on close.
            self._runner = web.AppRunner(app, access_log=None, shutdown_timeout=1.0)
            await self._runner.setup()
            site = web.TCPSite(self._runner, bind, 0)
            await site.start()
            port = self._runner.addresses[0][1]
            self.uri = f"http://{self.host}:{port}/"
            self._server = await asyncio.start_server(self._accept, bind, 0)
            self.tcpros_port = self._server.sockets[0].getsockname()[1]
        except BaseException:
            await self.close(unregister=False)
            raise
        self._registrar = asyncio.get_running_loop().create_task(self._register_loop())

    async def close(self, *, unregister: bool = True) -> None:
        """Unregister from the master and close every server and connection."""
        if unregister and self.uri:
            calls = [("unregisterPublisher", (name, self.uri)) for name in self.publications]
            calls += [("unregisterSubscriber", (name, self.uri)) for name in self.subscriptions]
            rosrpc = f"rosrpc://{self.host}:{self.tcpros_port}"
            calls += [("unregisterService", (name, rosrpc)) for name in self.services]
            with contextlib.suppress(Exception):
                await asyncio.wait_for(self._multicall(calls), 10)
        if self._registrar is not None:
            self._registrar.cancel()
            await asyncio.gather(self._registrar, return_exceptions=True)
        self._pending.clear()
        self._idle.set()
        for task in list(self._tasks):
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        for subscription in self.subscriptions.values():
            subscription.close()
        for publication in self.publications.values():
            for connection in list(publication.connections):
                connection.close()
        if self._server is not None:
            self._server.close()
            self._server = None
        if self._runner is not None:
            await self._runner.cleanup()
            self._runner = None
        if self._session is not None:
            await self._session.close()
            self._session = None

    def spawn(self, coroutine: Coroutine[Any, Any, Any]) -> None:
        """Run a coroutine the node owns (cancelled when it closes)."""
        task = asyncio.get_running_loop().create_task(coroutine)
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    # ------------------------------------------------------------------ master calls

    async def _xmlrpc(self, uri: str, method: str, params: tuple[Any, ...]) -> Any:
        if self._session is None:
            raise MasterError("the node is not started")
        body = xmlrpc.client.dumps(params, method, allow_none=False)
        async with self._session.post(uri, data=body, headers={"Content-Type": "text/xml"}) as response:
            text = await response.read()
        (result,), _ = xmlrpc.client.loads(text)
        return result

    async def master_call(self, method: str, *params: Any) -> Any:
        """Call the master; return the value of a successful (code 1) answer."""
        try:
            code, message, value = await self._xmlrpc(self.master_uri, method, (self.name, *params))
        except (aiohttp.ClientError, OSError, TimeoutError, xmlrpc.client.Error, ValueError) as exc:
            raise MasterError(f"ROS master {self.master_uri} did not answer {method}: {exc}") from None
        if code != 1:
            raise MasterError(f"ROS master refused {method}{params}: {message}")
        return value

    async def _multicall(self, calls: list[tuple[str, tuple[Any, ...]]]) -> list[Any]:
        """Make many master calls in as few requests as possible; failures come back as exceptions."""
        results: list[Any] = []
        for start in range(0, len(calls), BATCH):
            chunk = calls[start : start + BATCH]
            request = [{"methodName": m, "params": [self.name, *p]} for m, p in chunk]
            try:
                answers = await self._xmlrpc(self.master_uri, "system.multicall", (request,))
            except (aiohttp.ClientError, OSError, TimeoutError, xmlrpc.client.Error, ValueError) as exc:
                error = MasterError(f"ROS master {self.master_uri} did not answer: {exc}")
                results.extend(error for _ in chunk)
                continue
            for (method, params), answer in zip(chunk, answers, strict=True):
                if isinstance(answer, dict) or answer[0][0] != 1:
                    text = answer.get("faultString") if isinstance(answer, dict) else answer[0][1]
                    results.append(MasterError(f"ROS master refused {method} {params[0]}: {text}"))
                else:
                    results.append(answer[0][2])
        return results

    def _enqueue(self, method: str, *params: Any) -> None:
        self._pending.append((method, params))
        self._idle.clear()
        self._wake.set()

    async def _register_loop(self) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while self._pending:
                # Publishers first, so subscribers find them in their answer and nobody is notified twice.
                batch = sorted(self._pending[: BATCH * 4], key=lambda call: call[0] != "registerPublisher")
                del self._pending[: BATCH * 4]
                results = await self._multicall(batch)
                for (method, params), result in zip(batch, results, strict=True):
                    if isinstance(result, MasterError):
                        self._errors.append(result)
                    elif method == "registerSubscriber":
                        subscription = self.subscriptions.get(params[0])
                        if subscription is not None:
                            subscription.update(result, complete=False)
                batch = results = []  # nothing of a finished batch outlives it
            self._idle.set()

    async def settle(self) -> list[MasterError]:
        """Wait until every registration queued so far was sent; return (and forget) those refused."""
        await self._idle.wait()
        errors, self._errors = self._errors, []
        return errors

    # ------------------------------------------------------------------ topics and services

    def advertise(self, name: str, type_: str) -> Publication:
        """Publish a topic; the registration goes with the next batch (``settle`` waits for it)."""
        publication = self.publications.get(name)
        if publication is None:
            publication = self.publications[name] = Publication(name, type_)
        self._enqueue("registerPublisher", name, type_, self.uri)
        return publication

    def unadvertise(self, name: str) -> None:
        """Stop publishing a topic and close its subscribers' connections."""
        publication = self.publications.pop(name, None)
        if publication is not None:
            for connection in list(publication.connections):
                connection.close()
            self._enqueue("unregisterPublisher", name, self.uri)

    def subscribe(self, name: str, type_: str, callback: MessageCallback) -> Subscription:
        """Subscribe to a topic; the registration goes with the next batch (``settle`` waits for it)."""
        subscription = self.subscriptions.get(name)
        if subscription is None:
            subscription = self.subscriptions[name] = Subscription(self, name, type_, callback)
        self._enqueue("registerSubscriber", name, type_, self.uri)
        return subscription

    def unsubscribe(self, name: str) -> None:
        """Stop subscribing to a topic."""
        subscription = self.subscriptions.pop(name, None)
        if subscription is not None:
            subscription.close()
            self._enqueue("unregisterSubscriber", name, self.uri)

    def advertise_service(self, name: str, handler: ServiceHandler) -> None:
        """Serve a service; each client connection is handed to ``handler`` after its header."""
        self.services[name] = handler
        self._enqueue("registerService", name, f"rosrpc://{self.host}:{self.tcpros_port}", self.uri)

    def unadvertise_service(self, name: str) -> None:
        """Stop serving a service."""
        if self.services.pop(name, None) is not None:
            self._enqueue("unregisterService", name, f"rosrpc://{self.host}:{self.tcpros_port}")

    async def lookup_service(self, name: str) -> tuple[str, int] | None:
        """Return where a service is served, or None when nobody serves it."""
        try:
            uri = await self.master_call("lookupService", name)
        except MasterError:
            return None
        parts = urlsplit(uri)
        if parts.scheme != "rosrpc" or not parts.hostname or not parts.port:
            return None
        return parts.hostname, parts.port

    def on_publisher_header(self, subscription: Subscription, inbound: Inbound) -> None:
        """Pass a publisher's connection header to whoever owns the node."""
        if self._header_hook is not None:
            self._header_hook(subscription, inbound)

    async def connect(self, subscription: Subscription, publisher: str) -> None:
        """Ask a publisher for a TCPROS connection and open it."""
        try:
            code, message, protocol = await self._xmlrpc(
                publisher, "requestTopic", (self.name, subscription.name, [["TCPROS"]])
            )
            if code != 1 or not protocol or protocol[0] != "TCPROS":
                raise MasterError(message or "no TCPROS")
            _, host, port = protocol
            await asyncio.get_running_loop().create_connection(
                lambda: self._inbound(subscription, publisher), host, int(port)
            )
        except (aiohttp.ClientError, OSError, TimeoutError, xmlrpc.client.Error, ValueError, MasterError) as exc:
            logger.info("%s: cannot connect to publisher %s: %s", subscription.name, publisher, exc)
            if subscription.connections.get(publisher) is None:
                subscription.connections.pop(publisher, None)

    def _inbound(self, subscription: Subscription, publisher: str) -> Inbound:
        inbound = Inbound(subscription, publisher)
        if publisher in subscription.connections and self.subscriptions.get(subscription.name) is subscription:
            subscription.connections[publisher] = inbound
        return inbound

    # ------------------------------------------------------------------ TCPROS server

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        nodelay(writer.transport)
        try:
            header = await asyncio.wait_for(read_header(reader), 30)
        except (asyncio.IncompleteReadError, HeaderError, TimeoutError, ConnectionError):
            writer.close()
            return
        if "service" in header:
            handler = self.services.get(header["service"])
            if handler is None:
                writer.write(encode_header({"error": f"{self.name} does not serve {header['service']}"}))
                writer.close()
                return
            try:
                await handler(header, reader, writer)
            finally:
                writer.close()
            return
        publication = self.publications.get(header.get("topic", ""))
        if publication is None:
            writer.write(encode_header({"error": f"{self.name} does not publish {header.get('topic')}"}))
            writer.close()
            return
        reply = publication.reply_header(header, self.name)
        writer.write(encode_header(reply))
        if "error" in reply:
            writer.close()
            return
        outbound = Outbound(publication, writer, header.get("callerid", ""))
        if not publication.connections:
            publication.connections = []
        publication.connections.append(outbound)
        if publication.on_connect is not None:
            publication.on_connect(outbound)
        try:
            while await reader.read(4096):  # subscribers send nothing after their header
                pass
        except ConnectionError:
            pass
        finally:
            outbound.close()

    # ------------------------------------------------------------------ slave API

    async def _slave_request(self, request: web.Request) -> web.Response:
        try:
            params, method = xmlrpc.client.loads(await request.read())
            result = self._slave_call(method or "", params)
            body = xmlrpc.client.dumps((result,), methodresponse=True, allow_none=False)
        except Exception as exc:  # a peer's bad call is answered, never raised into the server
            body = xmlrpc.client.dumps(xmlrpc.client.Fault(1, str(exc)), methodresponse=True)
        return web.Response(body=body.encode(), content_type="text/xml")

    def _slave_call(self, method: str, params: tuple[Any, ...]) -> Any:
        if method == "requestTopic":
            _, topic, protocols = params
            if topic not in self.publications:
                return [0, f"{self.name} does not publish {topic}", []]
            if not any(p and p[0] == "TCPROS" for p in protocols):
                return [0, "only TCPROS is supported", []]
            return [1, "ready on TCPROS", ["TCPROS", self.host, self.tcpros_port]]
        if method == "publisherUpdate":
            _, topic, publishers = params
            subscription = self.subscriptions.get(topic)
            if subscription is not None:
                subscription.update(publishers, complete=True)
            return [1, "", 0]
        if method == "getPid":
            return [1, "", os.getpid()]
        if method == "getMasterUri":
            return [1, "", self.master_uri]
        if method == "getPublications":
            return [1, "", [[p.name, p.type] for p in self.publications.values()]]
        if method == "getSubscriptions":
            return [1, "", [[s.name, s.type] for s in self.subscriptions.values()]]
        if method == "getBusStats":
            return [1, "", [[], [], []]]
        if method == "getBusInfo":
            return [1, "", self._bus_info()]
        if method == "paramUpdate":
            return [1, "", 0]
        if method == "shutdown":
            # The router belongs to its Skill, not to whoever runs `rosnode kill`.
            logger.warning("%s: ignoring a shutdown request: %s", self.name, params[1:] or "")
            return [1, "the Skill Router stops with its Skill", 0]
        raise ValueError(f"unknown method {method!r}")

    def _bus_info(self) -> list[list[Any]]:
        info: list[list[Any]] = []
        for publication in self.publications.values():
            for connection in publication.connections:
                info.append([next(self._ids), connection.callerid, "o", "TCPROS", publication.name, True])
        for subscription in self.subscriptions.values():
            for uri, inbound in subscription.connections.items():
                if inbound is not None and inbound.header is not None:
                    info.append([next(self._ids), uri, "i", "TCPROS", subscription.name, True])
        return info
