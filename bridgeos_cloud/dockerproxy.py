"""A Docker Engine API proxy that lets the cloud orchestrate Swarm services and nothing more.

The deployed stack's worker and daphne reach Docker only through it (DOCKER_HOST=tcp://docker-proxy:2375):
the raw socket is root on the host, and a compromised cloud process should not be. It forwards the calls
skills/cloud/swarm.py makes (services, tasks, networks, nodes, image pulls and reads, info, version,
_ping, and GET reads of containers) and answers everything else 403 with a JSON ``{"message": ...}``
naming what was refused. Service specs are checked too: no host bind mounts outside the cloud's volume
directory, no privileges, no added capabilities, no host PID namespace.

    python -m bridgeos_cloud.dockerproxy --listen 0.0.0.0:2375 --socket /var/run/docker.sock --volumes-dir DIR

Each client connection carries one request: the proxy asks the engine to close after answering and
relays the answer's bytes as they come, so streams (logs, pulls, stats) stream.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import os
import posixpath
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any
from urllib.parse import parse_qs, urlsplit

logger = logging.getLogger("bridgeos.dockerproxy")

# A request head or body past these is not one the orchestration sends.
MAX_HEAD_BYTES = 64 * 1024
MAX_BODY_BYTES = 4 * 1024 * 1024
RELAY_CHUNK = 64 * 1024

_VERSION = re.compile(r"^/v\d+(\.\d+)?(?=/)")
_ID = r"[^/]+"
# (method, path pattern): what the orchestration uses. Image names may hold slashes (repo/name).
ALLOWED: tuple[tuple[str, re.Pattern[str]], ...] = tuple(
    (method, re.compile(f"^{pattern}$"))
    for method, pattern in [
        ("GET", "/_ping"),
        ("HEAD", "/_ping"),
        ("GET", "/version"),
        ("GET", "/info"),
        ("GET", "/services"),
        ("GET", f"/services/{_ID}"),
        ("GET", f"/services/{_ID}/logs"),
        ("POST", "/services/create"),
        ("POST", f"/services/{_ID}/update"),
        ("DELETE", f"/services/{_ID}"),
        ("GET", "/tasks"),
        ("GET", f"/tasks/{_ID}"),
        ("GET", f"/tasks/{_ID}/logs"),
        ("GET", "/networks"),
        ("GET", f"/networks/{_ID}"),
        ("POST", "/networks/create"),
        ("DELETE", f"/networks/{_ID}"),
        ("GET", "/nodes"),
        ("GET", f"/nodes/{_ID}"),
        ("GET", "/images/json"),
        ("GET", "/images/.+/json"),
        ("GET", "/images/.+/history"),
        ("GET", "/distribution/.+/json"),
        ("POST", "/images/create"),
        ("GET", "/containers/json"),
        ("GET", f"/containers/{_ID}/json"),
        ("GET", f"/containers/{_ID}/stats"),
        ("GET", f"/containers/{_ID}/logs"),
    ]
)
SPEC_CHECKED = re.compile(r"^/services/(create|[^/]+/update)$")
# Stopping a container is allowed for a cloud copy's task alone: the orchestration stops the task
# of a removed service at once rather than at Swarm's next pass; the stack's own containers
# (PostgreSQL, daphne) carry no such label and stay out of reach.
STOPPABLE = re.compile(r"^/containers/([A-Za-z0-9][A-Za-z0-9_.-]*)/stop$")
CLOUD_COPY_LABEL = "io.bridgeos.cloud"
NETWORK_DRIVERS = ("overlay", "bridge")


class Refused(Exception):
    """A request the proxy will not forward; its text says what and why."""


@dataclass(frozen=True)
class Policy:
    """What service specs may ask for: host bind mounts only under ``volumes_dir``."""

    volumes_dir: str

    def check(self, method: str, target: str, body: bytes) -> None:
        """Raise Refused unless the request is one the orchestration makes, with a harmless spec."""
        path = strip_version(urlsplit(target).path)
        if any(part in ("..", ".") for part in path.split("/")) or "%2e" in path.lower():
            raise Refused(f"{method} {path}: a path with dot segments is refused")
        if not any(method == allowed and pattern.match(path) for allowed, pattern in ALLOWED):
            detail = ""
            if method == "POST" and path == "/containers/create" and _privileged(body):
                detail = " with HostConfig.Privileged (a privileged container owns the host)"
            raise Refused(
                f"{method} {path}{detail} is refused: this proxy forwards only the Engine API calls the"
                " bridgeOS orchestration uses (services, tasks, networks, nodes, image pulls and reads, info,"
                " version, _ping, container reads)"
            )
        if method == "POST" and SPEC_CHECKED.match(path):
            self.check_service_spec(_json(body, path))
        if method == "POST" and path == "/networks/create":
            driver = str(_json(body, path).get("Driver") or "bridge")
            if driver not in NETWORK_DRIVERS:
                # macvlan, ipvlan and the like put containers on the host's own segment.
                raise Refused(f"a network with driver {driver!r} is refused (allowed: {', '.join(NETWORK_DRIVERS)})")
        if method == "POST" and path == "/images/create" and "fromSrc" in parse_qs(urlsplit(target).query):
            raise Refused("POST /images/create?fromSrc (an image import) is refused: only pulls are forwarded")

    def check_service_spec(self, spec: Mapping[str, Any]) -> None:
        """Raise Refused for a service spec asking for host access or privileges."""
        template = spec.get("TaskTemplate") or {}
        container = template.get("ContainerSpec") or {}
        if not isinstance(container, Mapping):
            raise Refused("the service spec's TaskTemplate.ContainerSpec is not an object")
        if container.get("Privileges"):
            raise Refused("a service spec with ContainerSpec.Privileges is refused (no privileges for cloud copies)")
        for key in ("CapabilityAdd", "Capabilities"):
            if container.get(key):
                raise Refused(f"a service spec with ContainerSpec.{key} {container[key]} is refused")
        for key in ("PidMode", "Pid"):
            if str(container.get(key) or "").lower() == "host":
                raise Refused(f"a service spec with ContainerSpec.{key}=host (the host's PID namespace) is refused")
        for mount in container.get("Mounts") or []:
            self._check_mount(mount)

    def _check_mount(self, mount: Mapping[str, Any]) -> None:
        kind = str(mount.get("Type") or "volume")
        source = str(mount.get("Source") or "")
        if kind == "bind":
            if not self.volumes_dir or not _under(source, self.volumes_dir):
                raise Refused(
                    f"a bind mount of {source or 'nothing'!r} is refused: cloud copies may bind only"
                    f" directories under {self.volumes_dir or '(none configured)'}"
                )
        elif kind == "volume":
            options = ((mount.get("VolumeOptions") or {}).get("DriverConfig") or {}).get("Options") or {}
            if options:
                # The local driver's device/o options bind any host path, bypassing the check above.
                raise Refused(f"a volume mount with driver options {sorted(options)} is refused")
        elif kind != "tmpfs":
            raise Refused(f"a mount of type {kind!r} is refused (bind under the volume directory, volume, tmpfs)")


def strip_version(path: str) -> str:
    """Drop an API version prefix (``/v1.47/info`` -> ``/info``)."""
    return _VERSION.sub("", path, count=1)


def _under(source: str, root: str) -> bool:
    if not source.startswith("/"):
        return False
    normal, base = posixpath.normpath(source), posixpath.normpath(root)
    return normal == base or normal.startswith(base.rstrip("/") + "/")


def _json(body: bytes, path: str) -> Mapping[str, Any]:
    try:
        value = json.loads(body or b"{}")
    except ValueError:
        raise Refused(f"POST {path}: the body is not JSON") from None
    if not isinstance(value, Mapping):
        raise Refused(f"POST {path}: the body is not a JSON object")
    return value


def _privileged(body: bytes) -> bool:
    with contextlib.suppress(ValueError, AttributeError):
        return bool(json.loads(body or b"{}").get("HostConfig", {}).get("Privileged"))
    return False


# --------------------------------------------------------------------------- the HTTP side


@dataclass
class Request:
    """One parsed request: its line, headers (lower-case names) and body."""

    method: str
    target: str
    version: str
    headers: list[tuple[str, str]]
    body: bytes

    def header(self, name: str) -> str:
        return next((value for key, value in self.headers if key == name), "")


class BadRequest(Exception):
    """The client sent something that is not an HTTP/1.1 request we can read."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


async def read_request(reader: asyncio.StreamReader) -> Request | None:
    """Read one request head and its body (Content-Length or chunked); None at a clean EOF."""
    try:
        head = await reader.readuntil(b"\r\n\r\n")
    except asyncio.IncompleteReadError as exc:
        if not exc.partial.strip():
            return None
        raise BadRequest(400, "the request head ended early") from None
    except asyncio.LimitOverrunError:
        raise BadRequest(431, f"the request head is larger than {MAX_HEAD_BYTES} bytes") from None
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ")
    if len(parts) != 3 or not parts[2].startswith("HTTP/1."):
        raise BadRequest(400, f"not an HTTP/1.x request line: {lines[0][:100]!r}")
    headers = []
    for line in lines[1:]:
        if line:
            name, sep, value = line.partition(":")
            if not sep:
                raise BadRequest(400, f"not a header line: {line[:100]!r}")
            headers.append((name.strip().lower(), value.strip()))
    request = Request(parts[0].upper(), parts[1], parts[2], headers, b"")
    if request.header("transfer-encoding").lower() == "chunked":
        request.body = await _read_chunked(reader)
    elif length := request.header("content-length"):
        if not length.isdigit():
            raise BadRequest(400, f"Content-Length {length!r} is not a number")
        if int(length) > MAX_BODY_BYTES:
            raise BadRequest(413, f"a body of {length} bytes is more than this proxy reads ({MAX_BODY_BYTES})")
        request.body = await reader.readexactly(int(length))
    return request


async def _read_chunked(reader: asyncio.StreamReader) -> bytes:
    body = bytearray()
    while True:
        size_line = (await reader.readuntil(b"\r\n")).split(b";")[0].strip()
        try:
            size = int(size_line, 16)
        except ValueError:
            raise BadRequest(400, "a malformed chunk size") from None
        if size == 0:
            await reader.readuntil(b"\r\n")  # the last chunk's terminator (no trailers are sent by clients)
            return bytes(body)
        if len(body) + size > MAX_BODY_BYTES:
            raise BadRequest(413, f"a body larger than this proxy reads ({MAX_BODY_BYTES} bytes)")
        body += await reader.readexactly(size)
        await reader.readexactly(2)


def error_response(status: int, message: str) -> bytes:
    """Return a complete HTTP answer with Docker's error shape, closing the connection."""
    reasons = {
        400: "Bad Request",
        403: "Forbidden",
        413: "Payload Too Large",
        431: "Header Too Large",
        502: "Bad Gateway",
    }
    body = json.dumps({"message": message}).encode()
    head = (
        f"HTTP/1.1 {status} {reasons.get(status, 'Error')}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n"
    )
    return head.encode() + body


def upstream_head(request: Request) -> bytes:
    """Rebuild the request for the engine: one request per connection, the body sent with its length."""
    skip = {"connection", "keep-alive", "transfer-encoding", "content-length", "upgrade", "proxy-connection"}
    lines = [f"{request.method} {request.target} HTTP/1.1"]
    lines += [f"{name}: {value}" for name, value in request.headers if name not in skip]
    if request.body or request.method in ("POST", "PUT"):
        lines.append(f"Content-Length: {len(request.body)}")
    lines.append("Connection: close")
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1")


class DockerProxy:
    """Serve the filtered Engine API on a TCP address, forwarding to the engine's unix socket."""

    def __init__(self, socket_path: str, policy: Policy) -> None:
        self.socket_path = socket_path
        self.policy = policy

    async def handle(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Answer one request on the connection, then close it."""
        peer = writer.get_extra_info("peername")
        try:
            try:
                request = await read_request(reader)
                if request is None:
                    return
                if request.header("upgrade"):
                    raise Refused(f"{request.method} {request.target}: connection upgrades (attach, exec) are refused")
                stop = STOPPABLE.match(strip_version(urlsplit(request.target).path))
                if request.method == "POST" and stop:
                    await self._check_cloud_copy(stop.group(1))
                else:
                    self.policy.check(request.method, request.target, request.body)
            except BadRequest as exc:
                writer.write(error_response(exc.status, str(exc)))
                return
            except Refused as exc:
                logger.warning("refused for %s: %s", peer, exc)
                writer.write(error_response(403, str(exc)))
                return
            if request.method not in ("GET", "HEAD"):
                # What changed on the engine, and for whom: the operator's trail of the orchestration's writes.
                logger.info("forwarding for %s: %s %s", peer, request.method, strip_version(request.target))
            await self._forward(request, writer)
        except (ConnectionError, asyncio.IncompleteReadError) as exc:
            logger.info("connection from %s ended: %s", peer, exc)
        finally:
            with contextlib.suppress(ConnectionError, OSError):
                await writer.drain()
                writer.close()
                await writer.wait_closed()

    async def _check_cloud_copy(self, container: str) -> None:
        """Raise Refused unless the container is a cloud copy's task (it carries the copy's label)."""
        try:
            reader, writer = await asyncio.open_unix_connection(self.socket_path)
        except OSError as exc:
            raise Refused(f"POST /containers/{container}/stop: the engine cannot be asked who it is ({exc})") from None
        try:
            # HTTP/1.0: the engine answers with a plain body and closes, nothing to de-chunk.
            writer.write(f"GET /containers/{container}/json HTTP/1.0\r\nHost: docker\r\n\r\n".encode())
            await writer.drain()
            # One read() returns what one segment carried; the inspect body often spans several.
            answer = b""
            while len(answer) <= MAX_BODY_BYTES and (chunk := await reader.read(65536)):
                answer += chunk
        finally:
            writer.close()
            with contextlib.suppress(ConnectionError, OSError):
                await writer.wait_closed()
        head, _, body = answer.partition(b"\r\n\r\n")
        try:
            labels = json.loads(body).get("Config", {}).get("Labels") or {} if b" 200 " in head[:16] else {}
        except (ValueError, AttributeError):
            labels = {}
        if CLOUD_COPY_LABEL not in labels:
            raise Refused(
                f"POST /containers/{container}/stop is refused: only a cloud copy's container"
                f" (labelled {CLOUD_COPY_LABEL}) may be stopped through this proxy"
            )

    async def _forward(self, request: Request, writer: asyncio.StreamWriter) -> None:
        try:
            up_reader, up_writer = await asyncio.open_unix_connection(self.socket_path)
        except OSError as exc:
            writer.write(error_response(502, f"the Docker engine at {self.socket_path} cannot be reached: {exc}"))
            return
        try:
            up_writer.write(upstream_head(request) + request.body)
            await up_writer.drain()
            # The engine closes after this one answer (Connection: close), so its end is the answer's end.
            while chunk := await up_reader.read(RELAY_CHUNK):
                writer.write(chunk)
                await writer.drain()
        finally:
            up_writer.close()
            with contextlib.suppress(ConnectionError, OSError):
                await up_writer.wait_closed()


async def serve(host: str, port: int, proxy: DockerProxy) -> None:
    """Listen until cancelled."""
    server = await asyncio.start_server(proxy.handle, host, port, limit=MAX_HEAD_BYTES)
    logger.info(
        "Docker API proxy on %s:%d -> %s (binds under %s)", host, port, proxy.socket_path, proxy.policy.volumes_dir
    )
    async with server:
        await server.serve_forever()


def main(argv: list[str] | None = None) -> None:
    """Run the proxy from the command line."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--listen", default="0.0.0.0:2375", help="HOST:PORT to serve on (default 0.0.0.0:2375)")
    parser.add_argument("--socket", default="/var/run/docker.sock", help="the engine's unix socket")
    parser.add_argument(
        "--volumes-dir",
        default=os.environ.get("BRIDGEOS_CLOUD_VOLUMES_DIR", ""),
        help="the only host directory service specs may bind-mount from (default: BRIDGEOS_CLOUD_VOLUMES_DIR)",
    )
    args = parser.parse_args(argv)
    host, sep, port = args.listen.rpartition(":")
    if not sep or not port.isdigit():
        parser.error(f"--listen {args.listen!r} is not HOST:PORT")
    if args.volumes_dir and not args.volumes_dir.startswith("/"):
        parser.error(f"--volumes-dir {args.volumes_dir!r} is not an absolute path")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    proxy = DockerProxy(args.socket, Policy(args.volumes_dir))
    with contextlib.suppress(KeyboardInterrupt):
        asyncio.run(serve(host.strip("[]") or "0.0.0.0", int(port), proxy))


if __name__ == "__main__":
    main()
