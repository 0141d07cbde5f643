"""Bring a component's image to the robot from the cloud's registry, with a token got with the robot's own credentials.

An image already in the robot's engine starts as it is, without touching any registry (an
offline robot restarts its Skills). One the engine lacks is pulled when its reference names a
registry (``host[:port]/repository[:tag|@digest]``): the agent asks the registry for its token
realm (Distribution's token authentication), asks that realm, which must be the robot's own
cloud, for a pull token with the robot's id and robot token, and hands the engine only that
short-lived token (``X-Registry-Auth``'s ``registrytoken``), never the robot token, which
never reaches a component either. Before pulling, the free disk under Docker's data root must
hold the image's compressed size three times over (the download and the unpacked layers) plus
a reserve; else the pull is refused as ``disk_full`` with the sizes named. Progress (bytes done
and total) goes to a callback as the engine reports it. Two components of one image share one
pull.

A pull cut by a lost link resumes: the engine itself retries a layer's download from where it
stopped (an HTTP Range request) for a while, and when it gives up, the agent pulls again with
growing gaps, up to ``retry_for`` seconds; layers already complete are kept by the engine and not
fetched again. Refusals (no such image, no token, a full disk) are not retried. After a pull,
the images no Skill uses any more are removed by the policy ``keep`` (the newest ``keep`` images
of each repository stay, besides every image a container or a Skill of the robot uses), so an
updated Skill does not fill the disk.
"""

from __future__ import annotations

import asyncio
import base64
import ipaddress
import logging
import re
import shutil
import ssl
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import aiohttp
import docker.errors
import requests
from docker.api import APIClient

from bridgeos_agent.imagerefs import split_reference
from bridgeos_agent.runtime.base import RuntimeFailure
from bridgeos_agent.runtime.usage import MIB

__all__ = ["DiskFull", "ImagePuller", "PullCut", "RegistryLogin", "unused_images"]

logger = logging.getLogger(__name__)

UNPACKED_FACTOR = 3  # the download and the unpacked layers, of a compressed size
MANIFEST_TYPES = (
    "application/vnd.docker.distribution.manifest.v2+json",
    "application/vnd.oci.image.manifest.v1+json",
    "application/vnd.docker.distribution.manifest.list.v2+json",
    "application/vnd.oci.image.index.v1+json",
)
CHALLENGE_PARAM = re.compile(r'(\w+)="([^"]*)"')
# What the engine says when a pull is refused rather than cut: no use pulling again.
REFUSED = re.compile(
    r"unauthorized|denied|not found|manifest unknown|no such|invalid reference|no space left", re.IGNORECASE
)
RETRY_GAPS = (1.0, 2.0, 4.0, 8.0, 15.0, 30.0)  # seconds between pulls again after a cut, then every 30 s

Progress = Callable[[int, int], None]  # (bytes done, bytes in all)


class DiskFull(RuntimeFailure):
    """The robot's disk cannot hold an image (``disk_full``)."""

    code = "disk_full"


class PullCut(RuntimeFailure):
    """A pull stopped by the network rather than refused: pulling again resumes it."""


@dataclass(frozen=True)
class RegistryLogin:
    """The robot's credentials, and the only token realm they are ever sent to: its own cloud."""

    robot: str
    token: str
    cloud: str  # scheme://host[:port] of the cloud
    ca_file: Path | None = None  # the cloud's CA, which also signs its registry's certificate

    @classmethod
    def for_cloud(cls, master: str, robot: str, token: str, ca_file: Path | None = None) -> RegistryLogin:
        """Build the login for the cloud an agent connects to (its ``--master`` URL, ws(s) or http(s))."""
        parts = urlsplit(master)
        scheme = {"ws": "http", "wss": "https"}.get(parts.scheme, parts.scheme)
        return cls(robot, token, f"{scheme}://{parts.netloc}", ca_file)

    def tls(self) -> ssl.SSLContext | bool:
        """Return how to verify the registry's and the realm's certificates (the cloud's CA when given)."""
        return ssl.create_default_context(cafile=str(self.ca_file)) if self.ca_file else True

    def owns(self, realm: str) -> bool:
        """Tell whether a token realm is this robot's cloud."""
        parts = urlsplit(realm)
        return f"{parts.scheme}://{parts.netloc}" == self.cloud


def _loopback(registry: str) -> bool:
    host = registry.rsplit(":", 1)[0].strip("[]") if registry.count(":") <= 1 else registry.strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class ImagePuller:
    """Pull the images a robot's engine lacks, one pull per image at a time."""

    def __init__(
        self,
        login: RegistryLogin | None,
        call: Callable[..., Any],
        *,
        disk_reserve: int = 256 * MIB,
        connect: Callable[[], Awaitable[APIClient]] | None = None,
        keep: int = 3,
        retry_for: float = 600.0,
    ) -> None:
        self.login = login
        self._call = call  # runs a blocking Docker SDK call in the runtime's thread pool
        self._connect = connect  # the runtime's engine client, for pulls ahead of any start
        self.disk_reserve = disk_reserve
        self.keep = keep  # images kept per repository besides those in use
        self.retry_for = retry_for  # seconds a cut pull is tried again before the start fails
        self.in_use: Callable[[], set[str]] = set  # the images the robot's Skills name (the controller's)
        self.ahead: set[str] = set()  # images pulled ahead for Skills added but not started yet
        self._pulls: dict[str, asyncio.Future[None]] = {}
        self.bytes_pulled = 0
        self.pulls_cut = 0

    async def ensure(self, api: APIClient, image: str, who: str, progress: Progress | None = None) -> bool:
        """Make sure the engine has ``image``; return whether it was pulled. RuntimeFailure says why not."""
        try:
            await self._call(api.inspect_image, image)
            return False
        except docker.errors.ImageNotFound:
            pass
        except docker.errors.APIError as exc:
            raise RuntimeFailure(f"{who}: Docker could not look up image {image!r}: {exc.explanation}") from None
        pending = self._pulls.get(image)
        if pending is None:
            pending = self._pulls[image] = asyncio.ensure_future(self._pull(api, image, who, progress))
            pending.add_done_callback(lambda done: self._ended(image, done))
        await asyncio.shield(pending)
        return True

    @property
    def pulling(self) -> list[str]:
        """Return the images being pulled now (a pull ends once the unused images are pruned after it)."""
        return list(self._pulls)

    def _ended(self, image: str, pull: asyncio.Future[None]) -> None:
        """Forget a finished pull; its failure is each waiter's to report, and seen even with none left."""
        self._pulls.pop(image, None)
        if not pull.cancelled():
            pull.exception()  # retrieved: a pull whose waiters were all cancelled (the agent stopping) is no error

    async def prefetch(self, skill: str, wanted: Mapping[str, list[str]], on_pull: Any = None) -> None:
        """Pull a Skill's images ahead of its start (image -> its components); a failure is the start's to say."""
        if self._connect is None or not wanted:
            return
        try:
            api = await self._connect()
        except RuntimeFailure as exc:
            logger.warning("skill %s: its images are not pulled ahead: %s", skill, exc)
            return
        self.ahead.update(wanted)
        for image, components in wanted.items():
            report = on_pull(skill, components[0], image) if on_pull is not None else None
            try:
                pulled = await self.ensure(api, image, f"skill {skill} ({', '.join(components)})", report)
                if not pulled and report is not None:
                    report(0, 0)  # already here: a rollout waiting for the bytes need not wait
            except RuntimeFailure as exc:
                logger.warning("pulling ahead for %s", exc)

    async def _pull(self, api: APIClient, image: str, who: str, progress: Progress | None) -> None:
        """Pull once, and again with growing gaps while the network cuts it; then prune what is unused."""
        deadline = time.monotonic() + self.retry_for
        for attempt in range(1_000_000):
            try:
                await self._pull_once(api, image, who, progress)
                break
            except PullCut as exc:
                self.pulls_cut += 1
                gap = RETRY_GAPS[min(attempt, len(RETRY_GAPS) - 1)]
                if time.monotonic() + gap > deadline:
                    raise RuntimeFailure(f"{exc}; gave up after {self.retry_for:.0f} s of trying again") from None
                logger.warning("%s; pulling again in %.0f s (complete layers are kept)", exc, gap)
                await asyncio.sleep(gap)
        await self._prepare(api, image)
        try:
            await self.prune(api)
        except (docker.errors.APIError, requests.exceptions.RequestException, OSError, RuntimeError) as exc:
            # Best effort: the next pull prunes again. RuntimeError: the agent is stopping (its pool shut).
            logger.warning("removing images no Skill uses: %s", exc)

    async def _prepare(self, api: APIClient, image: str) -> None:
        """Create and remove one container of a new image, so the component's first start finds it ready.

        The engine's first container of freshly unpacked layers costs it a few tens of
        milliseconds more than the next (measured by benchmarks/images.py); paid here, a start
        after a pull ahead is as quick as one with the image long there.
        """
        try:
            made = await self._call(api.create_container, image, command=["true"], network_disabled=True)
            await self._call(api.remove_container, made["Id"], force=True)
        except (docker.errors.APIError, requests.exceptions.RequestException, OSError, RuntimeError) as exc:
            logger.info("%s: preparing its first start did not work (%s); it starts all the same", image, exc)

    async def prune(self, api: APIClient) -> list[str]:
        """Remove the registry images the policy lets go (see ``unused_images``); return their ids."""
        images = await self._call(api.images)
        containers = await self._call(api.containers, all=True)
        used = {str(c.get("ImageID", "")) for c in containers}
        wanted = self.in_use() | self.ahead
        for image in images:
            if wanted & {*(image.get("RepoDigests") or ()), *(image.get("RepoTags") or ())}:
                used.add(str(image["Id"]))
        removed = []
        for image_id in unused_images(images, used, self.keep):
            try:
                await self._call(api.remove_image, image_id, force=False)
                removed.append(image_id)
            except docker.errors.APIError as exc:  # taken by a container made meanwhile: it stays
                logger.info("image %s stays: %s", image_id[:19], exc.explanation)
        if removed:
            logger.info("removed %d image(s) no Skill uses (keeping %d per repository)", len(removed), self.keep)
        return removed

    async def _pull_once(self, api: APIClient, image: str, who: str, progress: Progress | None) -> None:
        registry, repository, reference = split_reference(image)
        if registry is None:
            raise RuntimeFailure(
                f"{who}: image {image!r} is not on this robot and names no registry: push it to the cloud's "
                "registry and name it REGISTRY/NAMESPACE/NAME, or build it here (docker/build-images.sh builds "
                f"the bridgeos/* images; otherwise docker build -t {image} DIR)"
            )
        started = time.monotonic()
        base = f"{'http' if _loopback(registry) else 'https'}://{registry}"
        tls = self.login.tls() if self.login else True
        connector = aiohttp.TCPConnector(ssl=tls)
        async with aiohttp.ClientSession(timeout=aiohttp.ClientTimeout(total=30), connector=connector) as session:
            token = await self._token(session, base, repository, who, image)
            try:
                sizes = await self._layers(session, base, repository, reference, token, who)
            except (aiohttp.ClientError, OSError, TimeoutError) as exc:
                raise PullCut(f"{who}: reading {image!r}'s manifest was cut ({exc or type(exc).__name__})") from None
        total = sum(sizes.values())
        await self._check_disk(api, image, total, who)
        logger.info("%s: pulling %s (%.1f MB) from %s", who, image, total / 1e6, registry)
        auth = {"registrytoken": token} if token else None
        loop = asyncio.get_running_loop()
        report = None
        if progress is not None:
            report = lambda done: loop.call_soon_threadsafe(progress, done, total)  # noqa: E731
        done = await self._call(
            self._stream, api, f"{registry}/{repository}", reference, auth, sizes, report, who, image
        )
        self.bytes_pulled += done
        if progress is not None:
            progress(total, total)
        logger.info("%s: pulled %s in %.1f s", who, image, time.monotonic() - started)

    async def _token(self, session: aiohttp.ClientSession, base: str, repository: str, who: str, image: str) -> str:
        """Return a pull token from the registry's realm, or "" when the registry asks for none."""
        try:
            async with session.get(f"{base}/v2/") as answer:
                challenge = answer.headers.get("WWW-Authenticate", "")
                status = answer.status
        except (aiohttp.ClientError, OSError, TimeoutError) as exc:
            raise PullCut(
                f"{who}: image {image!r} is not on this robot and its registry {base} cannot be reached "
                f"({exc or type(exc).__name__})"
            ) from None
        if status == 200:
            return ""
        params = dict(CHALLENGE_PARAM.findall(challenge))
        realm = params.get("realm", "")
        if status != 401 or not challenge.lower().startswith("bearer ") or not realm:
            raise RuntimeFailure(f"{who}: registry {base} answered {status} without a token realm to pull {image!r}")
        if self.login is None or not self.login.owns(realm):
            cloud = self.login.cloud if self.login else "none"
            raise RuntimeFailure(
                f"{who}: registry {base} sends its clients to {realm} for tokens, not to this robot's cloud "
                f"({cloud}); the robot's credentials go to its own cloud only"
            )
        query = {"service": params.get("service", ""), "scope": f"repository:{repository}:pull"}
        basic = base64.b64encode(f"{self.login.robot}:{self.login.token}".encode()).decode()
        try:
            async with session.get(realm, params=query, headers={"Authorization": f"Basic {basic}"}) as answer:
                body = await answer.json(content_type=None) if answer.status == 200 else {}
                status = answer.status
        except (aiohttp.ClientError, OSError, TimeoutError, ValueError) as exc:
            raise PullCut(f"{who}: the cloud's token realm did not answer ({exc or type(exc).__name__})") from None
        token = body.get("token") or body.get("access_token") if isinstance(body, dict) else None
        if status != 200 or not token:
            raise RuntimeFailure(f"{who}: the cloud refused this robot a token to pull {image!r} ({status})")
        return str(token)

    async def _layers(
        self, session: aiohttp.ClientSession, base: str, repository: str, reference: str, token: str, who: str
    ) -> dict[str, int]:
        """Return an image's blobs' compressed sizes by the short id the engine reports them by ({} when unknown)."""
        headers = {"Accept": ", ".join(MANIFEST_TYPES)}
        if token:
            headers["Authorization"] = f"Bearer {token}"
        url = f"{base}/v2/{repository}/manifests/{reference}"
        for _ in range(2):  # an index names the linux/amd64 manifest: one more step
            async with session.get(url, headers=headers) as answer:
                if answer.status == 401 or answer.status == 403:
                    raise RuntimeFailure(
                        f"{who}: the registry refused this robot {repository}:{reference} ({answer.status})"
                    )
                if answer.status == 404:
                    raise RuntimeFailure(f"{who}: the registry has no image {repository}:{reference}")
                if answer.status != 200:
                    return {}
                manifest = await answer.json(content_type=None)
            if "manifests" in manifest:
                chosen = next(
                    (m for m in manifest["manifests"] if m.get("platform", {}).get("architecture") == "amd64"),
                    manifest["manifests"][0] if manifest["manifests"] else None,
                )
                if chosen is None:
                    return {}
                url = f"{base}/v2/{repository}/manifests/{chosen['digest']}"
                continue
            parts = [manifest.get("config") or {}, *manifest.get("layers", [])]
            return {str(part.get("digest", "")).partition(":")[2][:12]: int(part.get("size", 0)) for part in parts}
        return {}

    async def _check_disk(self, api: APIClient, image: str, size: int, who: str) -> None:
        """Refuse a pull the disk under Docker's data root cannot hold (``disk_full``)."""
        try:
            root = (await self._call(api.info)).get("DockerRootDir") or "/var/lib/docker"
            free = shutil.disk_usage(root).free
        except (docker.errors.APIError, OSError):
            return  # an engine elsewhere: its own disk is its to guard
        needed = size * UNPACKED_FACTOR + self.disk_reserve
        if free < needed:
            raise DiskFull(
                f"{who}: disk_full: image {image!r} needs about {needed / MIB:.0f} MiB ({size / MIB:.1f} MiB "
                f"compressed, x{UNPACKED_FACTOR}, plus a {self.disk_reserve / MIB:.0f} MiB reserve) and "
                f"{root} has {free / MIB:.0f} MiB free"
            )

    @staticmethod
    def _stream(
        api: APIClient,
        repository: str,
        reference: str,
        auth: dict[str, str] | None,
        sizes: dict[str, int],
        report: Callable[[int], Any] | None,
        who: str,
        image: str,
    ) -> int:
        """Pull through the engine (a worker thread), reporting bytes done; return the bytes downloaded."""
        done: dict[str, int] = {}  # short blob id -> bytes of it the robot holds
        fetched: set[str] = set()  # blobs downloaded, not found already there
        last = 0.0
        try:
            for chunk in api.pull(repository, tag=reference, stream=True, decode=True, auth_config=auth):
                if "error" in chunk or "errorDetail" in chunk:
                    said = str(chunk.get("errorDetail", {}).get("message") or chunk.get("error"))
                    failure = RuntimeFailure if REFUSED.search(said) else PullCut
                    raise failure(f"{who}: pulling {image!r} failed: {said}")
                layer, status = chunk.get("id", ""), chunk.get("status", "")
                detail = chunk.get("progressDetail") or {}
                if status == "Downloading" and "current" in detail:
                    done[layer] = int(detail["current"])
                    fetched.add(layer)
                elif status in ("Download complete", "Pull complete", "Already exists") and layer in sizes:
                    done[layer] = sizes[layer]
                    if status != "Already exists":
                        fetched.add(layer)
                now = time.monotonic()
                if report is not None and now - last >= 0.25:
                    last = now
                    report(sum(done.values()))
        except docker.errors.APIError as exc:
            refused = f"{who}: the registry would not give {image!r} to this robot"
            raise RuntimeFailure(f"{refused}: {exc.explanation}") from None
        except (OSError, requests.exceptions.RequestException) as exc:  # the engine's stream broke
            raise PullCut(f"{who}: pulling {image!r} was cut: {exc}") from None
        return sum(sizes.get(layer, done.get(layer, 0)) for layer in fetched)


def unused_images(images: list[Mapping[str, Any]], used: set[str], keep: int) -> list[str]:
    """Return the ids of pulled images to remove: unused, and beyond the newest ``keep`` unused of their repository.

    Only images from a registry count (a name with a registry host); images built on the robot
    are never touched. An image in several repositories stays when any of them keeps it.
    """
    by_repository: dict[str, list[Mapping[str, Any]]] = {}
    for image in images:
        names = [*(image.get("RepoDigests") or ()), *(image.get("RepoTags") or ())]
        for name in names:
            registry, repository, _ = split_reference(name)
            if registry is not None and "<none>" not in name:
                group = by_repository.setdefault(f"{registry}/{repository}", [])
                if image not in group:
                    group.append(image)
    kept: set[str] = set(used)
    candidates: set[str] = set()
    for group in by_repository.values():
        spare = [image for image in group if str(image["Id"]) not in used]
        newest = sorted(spare, key=lambda image: int(image.get("Created") or 0), reverse=True)
        kept.update(str(image["Id"]) for image in newest[:keep])
        candidates.update(str(image["Id"]) for image in newest[keep:])
    return sorted(candidates - kept)
