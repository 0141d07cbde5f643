"""Pin a Skill's images to digests: what a Skill runs is fixed when it is added, whatever its tags do later.

Every launch spec's image that names the cloud's own registry (``BRIDGEOS_REGISTRY_HOST``) is
resolved through that registry to the digest its tag points at now, and stored as
``host/repository:tag@sha256:…`` (Docker pulls and runs the digest; the tag stays for people
to read). The Skill's robot (or, for a release, its organization's robots) must be allowed to
pull it, by the same grant rules as the token server; a tag that does not exist, an image the
owner may not pull, or a registry that does not answer refuses the Skill with an error naming
the component and the image. Images of other registries and local images
(``bridgeos/ros:noetic``) are kept as written.
"""

from __future__ import annotations

import copy
import ipaddress
import ssl
from datetime import UTC, datetime
from typing import Any

import httpx
from django.conf import settings
from django.core.exceptions import ValidationError

from bridgeos_agent.imagerefs import split_reference
from robots.models import Robot
from teams.models import Organization

from . import tokens
from .services import organization_principal, robot_principal, signing_key

__all__ = ["pin_images", "registry_url"]

MANIFEST_TYPES = (
    "application/vnd.docker.distribution.manifest.v2+json",
    "application/vnd.oci.image.manifest.v1+json",
    "application/vnd.docker.distribution.manifest.list.v2+json",
    "application/vnd.oci.image.index.v1+json",
)


def registry_url(host: str) -> str:
    """Return how the cloud reaches its registry: BRIDGEOS_REGISTRY_URL, else http on loopback, https elsewhere."""
    configured = settings.BRIDGEOS["REGISTRY_URL"]
    if configured:
        return configured.rstrip("/")
    name = host.rsplit(":", 1)[0] if host.count(":") == 1 else host.strip("[]")
    try:
        loopback = name == "localhost" or ipaddress.ip_address(name).is_loopback
    except ValueError:
        loopback = False
    return f"{'http' if loopback else 'https'}://{host}"


def pin_images(config: dict[str, Any], owner: Robot | Organization) -> dict[str, Any]:
    """Return the config with its images of the cloud's registry pinned by digest; ValidationError if one cannot be.

    ``owner`` is the robot that runs it, or the organization whose robots will (a release's).
    """
    host = settings.BRIDGEOS["REGISTRY_HOST"]
    if not host:
        return config
    if isinstance(owner, Robot):
        principal, puller = robot_principal(owner), f"robot {owner.id}'s organization"
    else:
        principal, puller = organization_principal(owner), "organization"
    pinned = copy.deepcopy(config)
    problems: list[str] = []
    resolved: dict[str, str | ValueError] = {}  # an image named twice is asked about once
    ca = settings.BRIDGEOS["REGISTRY_CA"]
    verify = ssl.create_default_context(cafile=ca) if ca else True
    with httpx.Client(timeout=10, verify=verify) as client:
        for component_id, component in pinned.get("components", {}).items():
            for where in ("robot", "cloud"):
                launch = component.get(where) or {}
                image = launch.get("image")
                if not image:
                    continue
                registry, repository, reference = split_reference(image)
                if registry != host:
                    continue
                if image not in resolved:
                    try:
                        resolved[image] = _resolve(client, principal, puller, host, repository, reference, image)
                    except ValueError as exc:
                        resolved[image] = exc
                outcome = resolved[image]
                if isinstance(outcome, ValueError):
                    problems.append(f"components.{component_id}.{where}.image: {outcome}")
                else:
                    launch["image"] = outcome
    if problems:
        raise ValidationError({"config": problems}, code="invalid_config")
    return pinned


def _resolve(
    client: httpx.Client,
    principal: tokens.Principal,
    puller: str,
    host: str,
    repository: str,
    reference: str,
    image: str,
) -> str:
    """Return ``image`` pinned to the digest its reference names now; ValueError says why it cannot be."""
    scope = tokens.Scope("repository", repository, ("pull",))
    if "pull" not in tokens.granted(principal, scope):
        raise ValueError(
            f"{image!r}: {puller} {principal.username!r} may not pull {repository!r} "
            f"(its robots pull {principal.username}/...)"
        )
    conf = settings.BRIDGEOS
    claims = tokens.token_claims(
        principal,
        [scope],
        issuer=conf["REGISTRY_ISSUER"],
        audience=conf["REGISTRY_SERVICE"],
        now=datetime.now(UTC),
        ttl_s=60,
    )
    headers = {"Accept": ", ".join(MANIFEST_TYPES), "Authorization": f"Bearer {tokens.sign(claims, signing_key())}"}
    url = f"{registry_url(host)}/v2/{repository}/manifests/{reference}"
    try:
        answer = client.head(url, headers=headers)
    except httpx.HTTPError as exc:
        raise ValueError(f"{image!r}: the registry {host} did not answer ({exc or type(exc).__name__})") from None
    if answer.status_code == 404:
        raise ValueError(f"{image!r}: the registry has no {repository}:{reference} (push it first)")
    digest = answer.headers.get("Docker-Content-Digest", "")
    if answer.status_code != 200 or not digest.startswith("sha256:"):
        raise ValueError(f"{image!r}: the registry answered {answer.status_code} without a digest")
    tag = "" if reference.startswith("sha256:") else f":{reference}"
    return f"{host}/{repository}{tag}@{digest}"
